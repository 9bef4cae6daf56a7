-- ripplecal schema 2 on PostgreSQL: honest result statuses (as migrations/sqlite/0002, which rebuilds
-- the table: PostgreSQL alters the CHECK in place).

ALTER TABLE results DROP CONSTRAINT results_status_check;
ALTER TABLE results ADD CONSTRAINT results_status_check
    CHECK (status IN ('ok', 'below_target', 'no_authority', 'failed'));
ALTER TABLE results ADD COLUMN target_db DOUBLE PRECISION;
ALTER TABLE results ADD COLUMN noise_floor_db DOUBLE PRECISION;

-- results stored `ok` by earlier versions below the default 40 dB target were not ok
UPDATE results SET status = 'below_target',
       error = 'stored as ok by an earlier version at ' || round(suppression_db::numeric, 1)::text
               || ' dB, below the 40 dB target'
 WHERE status = 'ok' AND (suppression_db IS NULL OR suppression_db < 40.0);
