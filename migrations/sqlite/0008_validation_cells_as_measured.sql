-- ripplecal schema 8: a validation's cells are stored as they are measured (issue 18).
-- - map_validations.state gains 'running': the row is written when the LUT is in the drive and
--   updated after every point, so a crash keeps what was measured (the service marks it failed at its
--   next start, naming the LUT the drive holds). SQLite cannot alter a CHECK constraint: the table is
--   rebuilt, every row kept, its indexes made again.

CREATE TABLE map_validations_new (
    id                INTEGER PRIMARY KEY,
    map_id            INTEGER NOT NULL REFERENCES maps(id),
    job_id            INTEGER NOT NULL REFERENCES jobs(id),
    state             TEXT NOT NULL CHECK (state IN ('running', 'done', 'failed', 'cancelled')),
    error             TEXT,
    harmonic_order    INTEGER NOT NULL,
    options_json      TEXT NOT NULL,
    download_json     TEXT NOT NULL,
    summary_json      TEXT NOT NULL,
    cells_json        TEXT NOT NULL,
    bench_identity    TEXT NOT NULL,
    software_version  TEXT NOT NULL,
    started_at        TEXT NOT NULL,
    finished_at       TEXT
);

INSERT INTO map_validations_new (id, map_id, job_id, state, error, harmonic_order, options_json, download_json,
                                 summary_json, cells_json, bench_identity, software_version, started_at, finished_at)
SELECT id, map_id, job_id, state, error, harmonic_order, options_json, download_json, summary_json, cells_json,
       bench_identity, software_version, started_at, finished_at FROM map_validations;

DROP TABLE map_validations;
ALTER TABLE map_validations_new RENAME TO map_validations;
CREATE INDEX map_validations_by_map ON map_validations(map_id, id);
CREATE INDEX map_validations_by_job ON map_validations(job_id);
