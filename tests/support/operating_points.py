"""The operating points the tests share. OP1 is the paper's first point, {2.5 Nm, 2000 rpm, 12 V}: on the
emulator's paper-bench truth the injection that cancels its 6th harmonic is near gamma 3 deg, delta 280 deg."""

from __future__ import annotations

from service.model.operating_point import OperatingPoint

OP1 = {"torque_nm": 2.5, "speed_rpm": 2000, "udc_v": 12}  # as the API takes it (JSON body)
OP1_POINT = OperatingPoint(**OP1)  # as the service layer takes it
