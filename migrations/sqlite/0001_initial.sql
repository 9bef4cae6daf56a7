-- ripplecal schema 1: tokens, jobs, sweeps, results, maps.
-- Every result is self-describing: operating point, method and options, bench identity,
-- software version, timestamps, and the traces to redraw its plots.

CREATE TABLE api_tokens (
    id            INTEGER PRIMARY KEY,
    role          TEXT NOT NULL CHECK (role IN ('viewer', 'operator', 'admin')),
    token_sha256  TEXT NOT NULL UNIQUE,
    label         TEXT NOT NULL DEFAULT '',
    created_at    TEXT NOT NULL,
    revoked_at    TEXT
);

CREATE TABLE sweeps (
    id                INTEGER PRIMARY KEY,
    state             TEXT NOT NULL CHECK (state IN ('queued', 'running', 'paused', 'done', 'failed', 'cancelled')),
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
    finished_at       TEXT
);

CREATE TABLE jobs (
    id            INTEGER PRIMARY KEY,
    kind          TEXT NOT NULL CHECK (kind IN ('identification', 'sweep')),
    state         TEXT NOT NULL CHECK (state IN ('queued', 'running', 'done', 'failed', 'cancelled')),
    request_json  TEXT NOT NULL,
    sweep_id      INTEGER REFERENCES sweeps(id),
    result_id     INTEGER,
    error         TEXT,
    created_at    TEXT NOT NULL,
    started_at    TEXT,
    finished_at   TEXT
);

CREATE TABLE results (
    id                  INTEGER PRIMARY KEY,
    job_id              INTEGER REFERENCES jobs(id),
    sweep_id            INTEGER REFERENCES sweeps(id),
    torque_nm           REAL NOT NULL,
    speed_rpm           REAL NOT NULL,
    udc_v               REAL NOT NULL,
    harmonic_order      INTEGER NOT NULL,
    method              TEXT NOT NULL,
    options_json        TEXT NOT NULL,
    status              TEXT NOT NULL CHECK (status IN ('ok', 'no_authority', 'failed')),
    error               TEXT,
    theta_cos           REAL,
    theta_sin           REAL,
    gamma_deg           REAL,
    delta_deg           REAL,
    residual_a_c        REAL,
    residual_a_s        REAL,
    uncompensated_a_c   REAL,
    uncompensated_a_s   REAL,
    suppression_db      REAL,
    plant_time_s        REAL,
    windows_used        INTEGER,
    detail_json         TEXT NOT NULL DEFAULT '{}',
    traces_json         TEXT NOT NULL DEFAULT '{}',
    bench_identity      TEXT NOT NULL,
    software_version    TEXT NOT NULL,
    started_at          TEXT NOT NULL,
    finished_at         TEXT NOT NULL
);
CREATE INDEX results_sweep ON results(sweep_id);

CREATE TABLE maps (
    id                INTEGER PRIMARY KEY,
    sweep_id          INTEGER REFERENCES sweeps(id),
    harmonic_order    INTEGER NOT NULL,
    method            TEXT NOT NULL,
    axes_json         TEXT NOT NULL,
    bench_identity    TEXT NOT NULL,
    software_version  TEXT NOT NULL,
    created_at        TEXT NOT NULL
);

CREATE TABLE map_cells (
    map_id      INTEGER NOT NULL REFERENCES maps(id),
    result_id   INTEGER REFERENCES results(id),
    torque_nm   REAL NOT NULL,
    speed_rpm   REAL NOT NULL,
    udc_v       REAL NOT NULL,
    PRIMARY KEY (map_id, torque_nm, speed_rpm, udc_v)
);
