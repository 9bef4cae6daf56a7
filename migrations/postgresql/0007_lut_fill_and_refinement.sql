-- ripplecal schema 7 on PostgreSQL: the LUT holds where the motor runs (as
-- migrations/sqlite/0007_lut_fill_and_refinement.sql, which rebuilds jobs: PostgreSQL alters the CHECK
-- in place).

ALTER TABLE map_cells ADD COLUMN fill_theta_cos DOUBLE PRECISION;
ALTER TABLE map_cells ADD COLUMN fill_theta_sin DOUBLE PRECISION;
ALTER TABLE map_cells ADD COLUMN fill_source TEXT;

ALTER TABLE maps ADD COLUMN refined_from BIGINT REFERENCES maps(id);
ALTER TABLE maps ADD COLUMN provenance_json TEXT;

ALTER TABLE sweeps ADD COLUMN kind TEXT NOT NULL DEFAULT 'sweep' CHECK (kind IN ('sweep', 'refinement'));
ALTER TABLE sweeps ADD COLUMN source_map_id BIGINT REFERENCES maps(id);
ALTER TABLE sweeps ADD COLUMN refinement_json TEXT;

ALTER TABLE jobs DROP CONSTRAINT jobs_kind_check;
ALTER TABLE jobs ADD CONSTRAINT jobs_kind_check
    CHECK (kind IN ('identification', 'sweep', 'validation', 'refinement'));
