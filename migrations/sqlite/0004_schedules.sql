-- ripplecal schema 4: scheduled sweeps.
-- - schedules: a cron expression (5 fields, Debian cron semantics) in an IANA time zone and the sweep
--   request it submits. `last_due_at` (UTC) is the last firing handled (fired, skipped or missed):
--   the scheduler fires what falls due after it, so a restart finds the firings it missed.
--   A deleted schedule keeps its row (deleted_at) so its runs and sweeps still name it.
-- - schedule_runs: one row per firing handled, with its outcome and the sweep it submitted.
-- - sweeps.schedule_id: the schedule that submitted a sweep (NULL for a sweep started by hand).

CREATE TABLE schedules (
    id            INTEGER PRIMARY KEY,
    name          TEXT NOT NULL,
    cron          TEXT NOT NULL,
    timezone      TEXT NOT NULL,
    sweep_json    TEXT NOT NULL,
    enabled       INTEGER NOT NULL DEFAULT 1 CHECK (enabled IN (0, 1)),
    created_at    TEXT NOT NULL,
    updated_at    TEXT NOT NULL,
    last_due_at   TEXT NOT NULL,
    deleted_at    TEXT
);

CREATE TABLE schedule_runs (
    id            INTEGER PRIMARY KEY,
    schedule_id   INTEGER NOT NULL REFERENCES schedules(id),
    due_at        TEXT NOT NULL,
    fired_at      TEXT NOT NULL,
    outcome       TEXT NOT NULL CHECK (outcome IN ('started', 'queued', 'skipped', 'missed', 'failed')),
    sweep_id      INTEGER REFERENCES sweeps(id),
    note          TEXT
);
CREATE INDEX schedule_runs_by_schedule ON schedule_runs(schedule_id, id);

ALTER TABLE sweeps ADD COLUMN schedule_id INTEGER REFERENCES schedules(id);
