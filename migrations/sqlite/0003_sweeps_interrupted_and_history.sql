-- ripplecal schema 3: sweeps that survive the night.
-- - `interrupted`: the service stopped under a running sweep; it can be resumed.
-- - `pause_reason`: why a sweep is paused or interrupted (interlock, operator, shutdown).
-- - results.superseded_by: a sweep shows one result per operating point; an earlier attempt at the
--   same point (e.g. the point in flight when an interlock tripped) is kept as history and points
--   at the attempt that replaced it.

CREATE TABLE sweeps_new (
    id                INTEGER PRIMARY KEY,
    state             TEXT NOT NULL CHECK (state IN ('queued', 'running', 'paused', 'interrupted', 'done', 'failed', 'cancelled')),
    method            TEXT NOT NULL,
    harmonic_order    INTEGER NOT NULL,
    grid_json         TEXT NOT NULL,
    options_json      TEXT NOT NULL,
    total_points      INTEGER NOT NULL,
    done_points       INTEGER NOT NULL DEFAULT 0,
    failed_points     INTEGER NOT NULL DEFAULT 0,
    map_id            INTEGER,
    error             TEXT,
    bench_identity    TEXT NOT NULL,
    software_version  TEXT NOT NULL,
    created_at        TEXT NOT NULL,
    started_at        TEXT,
    finished_at       TEXT,
    pause_reason      TEXT
);

INSERT INTO sweeps_new (id, state, method, harmonic_order, grid_json, options_json, total_points, done_points,
                        failed_points, map_id, error, bench_identity, software_version, created_at, started_at,
                        finished_at)
SELECT id, state, method, harmonic_order, grid_json, options_json, total_points, done_points,
       failed_points, map_id, error, bench_identity, software_version, created_at, started_at, finished_at
FROM sweeps;

DROP TABLE sweeps;
ALTER TABLE sweeps_new RENAME TO sweeps;

ALTER TABLE results ADD COLUMN superseded_by INTEGER REFERENCES results(id);
CREATE INDEX results_sweep_current ON results(sweep_id, superseded_by);
