-- ripplecal schema 10: the torque a result ran at (issue 25: the envelope held on what the motor does).
-- results.torque_actual_nm: the drive's torque actual (0x6077 from its TPDO), mean over the result's
-- measurement, Nm; NULL for results from before schema 10 and for failures before anything was measured.
-- A result whose torque actual left its command beyond safety.torque_tolerance_fraction / torque_tolerance_nm
-- is never ok (service/model/limits.py torque_departure).

ALTER TABLE results ADD COLUMN torque_actual_nm DOUBLE PRECISION;
