-- ripplecal schema 5: raw recordings (service/store/recordings.py).
-- results.recording_json: what became of the result's raw DAQ recording (MF4 file), NULL where none
-- was attempted (recordings switched off, results from before schema 5):
-- {"format": "mf4", "path", "bytes", "samples", "counted_samples", "setpoints", "sample_rate_hz",
--  "written_at"} or with "error" (why it could not be written), and "deleted" once retention removed it.

ALTER TABLE results ADD COLUMN recording_json TEXT;
