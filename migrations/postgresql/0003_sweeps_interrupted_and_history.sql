-- ripplecal schema 3 on PostgreSQL: sweeps that survive the night (as migrations/sqlite/0003, which
-- rebuilds the sweeps table: PostgreSQL alters the CHECK in place).

ALTER TABLE sweeps DROP CONSTRAINT sweeps_state_check;
ALTER TABLE sweeps ADD CONSTRAINT sweeps_state_check
    CHECK (state IN ('queued', 'running', 'paused', 'interrupted', 'done', 'failed', 'cancelled'));
ALTER TABLE sweeps ADD COLUMN pause_reason TEXT;

ALTER TABLE results ADD COLUMN superseded_by BIGINT REFERENCES results(id);
CREATE INDEX results_sweep_current ON results(sweep_id, superseded_by);
