-- ripplecal schema 8 on PostgreSQL: a validation's cells are stored as they are measured (as
-- migrations/sqlite/0008_validation_cells_as_measured.sql, which rebuilds the table: PostgreSQL alters
-- the CHECK and the NOT NULL in place).

ALTER TABLE map_validations DROP CONSTRAINT map_validations_state_check;
ALTER TABLE map_validations ADD CONSTRAINT map_validations_state_check
    CHECK (state IN ('running', 'done', 'failed', 'cancelled'));
ALTER TABLE map_validations ALTER COLUMN finished_at DROP NOT NULL;
