-- ripplecal schema 9: a lab (issue 20): several benches, one service per bench, one database.
-- - benches: one row per bench name, written by the service that serves it (service/runs/lab.py): which
--   process holds the name (instance, a random id per process start; host, port, pid), its bench state,
--   what it runs, and last_seen (UTC ISO 8601), renewed about every second. A service claims the name
--   only if the row is its own, stopped, or not renewed within the stale limit. Keyed by the name: no
--   autoincrement, the same on SQLite and PostgreSQL.
-- - jobs.bench, sweeps.bench, schedules.bench: the bench the work is for. NULL: a row from before this
--   schema (one database, one bench): the first service to start on it adopts them as its own bench's.
-- - jobs.claimed_by: the service instance that queued it for its own bench or took it from the database
--   (NULL: waiting for whichever service serves its bench).
-- - jobs.updated_at, sweeps.updated_at: set on every write, so another bench's service can show progress.
-- - sweeps.control_request: pause | resume | cancel asked at another bench's service, for the sweep's own
--   bench's service to act on (within about a second); sweeps.control_note: what became of it if refused.

CREATE TABLE benches (
    name              TEXT PRIMARY KEY,
    instance          TEXT NOT NULL,
    host              TEXT NOT NULL,
    port              INTEGER,
    pid               INTEGER NOT NULL,
    state             TEXT NOT NULL DEFAULT 'starting',
    busy              INTEGER NOT NULL DEFAULT 0,
    running           TEXT,
    software_version  TEXT NOT NULL,
    started_at        TEXT NOT NULL,
    last_seen         TEXT NOT NULL,
    stopped_at        TEXT
);

ALTER TABLE jobs ADD COLUMN bench TEXT;
ALTER TABLE jobs ADD COLUMN claimed_by TEXT;
ALTER TABLE jobs ADD COLUMN updated_at TEXT;
ALTER TABLE sweeps ADD COLUMN bench TEXT;
ALTER TABLE sweeps ADD COLUMN updated_at TEXT;
ALTER TABLE sweeps ADD COLUMN control_request TEXT;
ALTER TABLE sweeps ADD COLUMN control_note TEXT;
ALTER TABLE schedules ADD COLUMN bench TEXT;

CREATE INDEX jobs_by_bench_state ON jobs(bench, state);
CREATE INDEX jobs_by_updated ON jobs(updated_at);
CREATE INDEX sweeps_by_updated ON sweeps(updated_at);
