-- ripplecal schema 11: run-ups (issue 27).
-- - runups: one row per run-up job (service/runs/runup.py): the request, the order analysis as measured
--   (result_json: speed bins, orders, amplitude and phase per order and bin, noise floor per bin), the
--   bench identity and software version, and its raw recording (recording_json, as results' recordings).
-- - jobs.kind gains 'runup' (SQLite cannot alter a CHECK constraint: the table is rebuilt, every row and
--   index kept; the migration runs with foreign keys off and checks them before it commits).

CREATE TABLE jobs_new (
    id            INTEGER PRIMARY KEY,
    kind          TEXT NOT NULL CHECK (kind IN ('identification', 'sweep', 'validation', 'refinement', 'runup')),
    state         TEXT NOT NULL CHECK (state IN ('queued', 'running', 'done', 'failed', 'cancelled')),
    request_json  TEXT NOT NULL,
    sweep_id      INTEGER REFERENCES sweeps(id),
    result_id     INTEGER,
    error         TEXT,
    created_at    TEXT NOT NULL,
    started_at    TEXT,
    finished_at   TEXT,
    bench         TEXT,
    claimed_by    TEXT,
    updated_at    TEXT
);

INSERT INTO jobs_new (id, kind, state, request_json, sweep_id, result_id, error, created_at, started_at, finished_at,
                      bench, claimed_by, updated_at)
SELECT id, kind, state, request_json, sweep_id, result_id, error, created_at, started_at, finished_at,
       bench, claimed_by, updated_at FROM jobs;

DROP TABLE jobs;
ALTER TABLE jobs_new RENAME TO jobs;
CREATE INDEX jobs_by_bench_state ON jobs(bench, state);
CREATE INDEX jobs_by_updated ON jobs(updated_at);

CREATE TABLE runups (
    id                INTEGER PRIMARY KEY,
    job_id            INTEGER NOT NULL REFERENCES jobs(id),
    state             TEXT NOT NULL CHECK (state IN ('done', 'failed', 'cancelled')),
    error             TEXT,
    request_json      TEXT NOT NULL,
    result_json       TEXT,
    recording_json    TEXT,
    bench_identity    TEXT NOT NULL,
    software_version  TEXT NOT NULL,
    started_at        TEXT NOT NULL,
    finished_at       TEXT NOT NULL
);
CREATE INDEX runups_by_job ON runups(job_id);
