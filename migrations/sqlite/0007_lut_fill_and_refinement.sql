-- ripplecal schema 7: the LUT holds where the motor runs (issue 17).
-- - map_cells.fill_*: a cell that stayed non-ok gets a LUT entry by the fill rule (service/maps/fill.py),
--   stored with the map so a LUT built today is built the same way tomorrow (its CRC does not move).
-- - maps.refined_from, maps.provenance_json: a refined map names the map it was refined from and how
--   (the refinement, its round, the cells it added).
-- - sweeps.kind, sweeps.source_map_id, sweeps.refinement_json: a refinement runs as a sweep of its own
--   kind (pause, resume, cancel, interruption and crash-resume as any sweep's), its state in JSON.
-- - jobs.kind gains 'refinement' (SQLite cannot alter a CHECK constraint: the table is rebuilt, every
--   row kept; the migration runs with foreign keys off and checks them before it commits).

ALTER TABLE map_cells ADD COLUMN fill_theta_cos REAL;
ALTER TABLE map_cells ADD COLUMN fill_theta_sin REAL;
ALTER TABLE map_cells ADD COLUMN fill_source TEXT;

ALTER TABLE maps ADD COLUMN refined_from INTEGER REFERENCES maps(id);
ALTER TABLE maps ADD COLUMN provenance_json TEXT;

ALTER TABLE sweeps ADD COLUMN kind TEXT NOT NULL DEFAULT 'sweep' CHECK (kind IN ('sweep', 'refinement'));
ALTER TABLE sweeps ADD COLUMN source_map_id INTEGER REFERENCES maps(id);
ALTER TABLE sweeps ADD COLUMN refinement_json TEXT;

CREATE TABLE jobs_new (
    id            INTEGER PRIMARY KEY,
    kind          TEXT NOT NULL CHECK (kind IN ('identification', 'sweep', 'validation', 'refinement')),
    state         TEXT NOT NULL CHECK (state IN ('queued', 'running', 'done', 'failed', 'cancelled')),
    request_json  TEXT NOT NULL,
    sweep_id      INTEGER REFERENCES sweeps(id),
    result_id     INTEGER,
    error         TEXT,
    created_at    TEXT NOT NULL,
    started_at    TEXT,
    finished_at   TEXT
);

INSERT INTO jobs_new (id, kind, state, request_json, sweep_id, result_id, error, created_at, started_at, finished_at)
SELECT id, kind, state, request_json, sweep_id, result_id, error, created_at, started_at, finished_at FROM jobs;

DROP TABLE jobs;
ALTER TABLE jobs_new RENAME TO jobs;
