-- ripplecal schema 6: a map proven in the drive's LUT mode (issue 11).
-- - jobs.kind gains 'validation' (SQLite cannot alter a CHECK constraint: the table is rebuilt,
--   every row kept; the migration runs with foreign keys off and checks them before it commits).
-- - map_validations: one row per validation job, whatever ended it (done, failed, cancelled): the
--   download receipt, the summary and every cell (grid points and midpoints) as JSON. A map's
--   latest validation is its newest row.

CREATE TABLE jobs_new (
    id            INTEGER PRIMARY KEY,
    kind          TEXT NOT NULL CHECK (kind IN ('identification', 'sweep', 'validation')),
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

CREATE TABLE map_validations (
    id                INTEGER PRIMARY KEY,
    map_id            INTEGER NOT NULL REFERENCES maps(id),
    job_id            INTEGER NOT NULL REFERENCES jobs(id),
    state             TEXT NOT NULL CHECK (state IN ('done', 'failed', 'cancelled')),
    error             TEXT,
    harmonic_order    INTEGER NOT NULL,
    options_json      TEXT NOT NULL,
    download_json     TEXT NOT NULL,
    summary_json      TEXT NOT NULL,
    cells_json        TEXT NOT NULL,
    bench_identity    TEXT NOT NULL,
    software_version  TEXT NOT NULL,
    started_at        TEXT NOT NULL,
    finished_at       TEXT NOT NULL
);
CREATE INDEX map_validations_by_map ON map_validations(map_id, id);
CREATE INDEX map_validations_by_job ON map_validations(job_id);
