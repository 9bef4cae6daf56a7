-- ripplecal schema 2: honest result statuses.
-- A result is `ok` only when it met its target; `below_target` is a finished identification that
-- did not reach it (with the reason). Every result reports the target it was held to and the
-- noise floor it measured. SQLite cannot alter a CHECK constraint: the table is rebuilt (the
-- migration runs with foreign keys off and checks them before it commits).

CREATE TABLE results_new (
    id                  INTEGER PRIMARY KEY,
    job_id              INTEGER REFERENCES jobs(id),
    sweep_id            INTEGER REFERENCES sweeps(id),
    torque_nm           REAL NOT NULL,
    speed_rpm           REAL NOT NULL,
    udc_v               REAL NOT NULL,
    harmonic_order      INTEGER NOT NULL,
    method              TEXT NOT NULL,
    options_json        TEXT NOT NULL,
    status              TEXT NOT NULL CHECK (status IN ('ok', 'below_target', 'no_authority', 'failed')),
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
    finished_at         TEXT NOT NULL,
    target_db           REAL,
    noise_floor_db      REAL
);

INSERT INTO results_new (id, job_id, sweep_id, torque_nm, speed_rpm, udc_v, harmonic_order, method, options_json,
                         status, error, theta_cos, theta_sin, gamma_deg, delta_deg, residual_a_c, residual_a_s,
                         uncompensated_a_c, uncompensated_a_s, suppression_db, plant_time_s, windows_used,
                         detail_json, traces_json, bench_identity, software_version, started_at, finished_at)
SELECT id, job_id, sweep_id, torque_nm, speed_rpm, udc_v, harmonic_order, method, options_json,
       status, error, theta_cos, theta_sin, gamma_deg, delta_deg, residual_a_c, residual_a_s,
       uncompensated_a_c, uncompensated_a_s, suppression_db, plant_time_s, windows_used,
       detail_json, traces_json, bench_identity, software_version, started_at, finished_at
FROM results;

-- results stored `ok` by earlier versions below the default 40 dB target were not ok
UPDATE results_new SET status = 'below_target',
       error = 'stored as ok by an earlier version at ' || printf('%.1f', suppression_db) || ' dB, below the 40 dB target'
 WHERE status = 'ok' AND (suppression_db IS NULL OR suppression_db < 40.0);

DROP TABLE results;
ALTER TABLE results_new RENAME TO results;
CREATE INDEX results_sweep ON results(sweep_id);
