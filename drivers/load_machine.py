"""The load machine that holds the bench speed: CiA 402 profile velocity (docs/interfaces.md).

Shares all CiA 402 master logic with the drive (drivers.cia402_master); only the mode, the speed
setpoint and its safety step (speed 0 before the power stage goes off) are its own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from drivers import LOAD_EDS
from drivers.canopen_bus import CanBus
from drivers.cia402 import State402
from drivers.cia402_master import Cia402Master

MODE_PROFILE_VELOCITY = 3

OD_VELOCITY_ACTUAL = 0x606C  # I32, rpm
OD_TORQUE_ACTUAL = 0x6077  # I16, scaled by LoadClient.torque_scale_nm (the contract gives no unit)
OD_TARGET_VELOCITY = 0x60FF  # I32, rpm

INT32_MAX = 2**31 - 1


@dataclass(frozen=True)
class LoadStatus:
    state: State402
    speed_rpm: float
    torque_nm: float


class LoadClient(Cia402Master):
    """CANopen client of the load machine (default node 6), SDO only.

    torque_scale_nm: newton-metres per count of the load's 0x6077 (the load EDS has no rated-torque
    object; 0.001 reads the value as mNm).
    """

    device_kind = "load machine"

    def __init__(self, bus: CanBus, node_id: int, sdo_timeout_s: float = 0.5, torque_scale_nm: float = 0.001):
        super().__init__(bus, node_id, LOAD_EDS, MODE_PROFILE_VELOCITY, sdo_timeout_s)
        self.torque_scale_nm = torque_scale_nm

    def _safe_steps(self):
        return [("target velocity 0", lambda: self.write(OD_TARGET_VELOCITY, 0, 0))]

    def set_speed_rpm(self, speed_rpm: float) -> int:
        """Target velocity 0x60FF in rpm (integer on the wire). Returns the value sent."""
        if not math.isfinite(speed_rpm) or abs(speed_rpm) > INT32_MAX:
            raise ValueError(f"speed {speed_rpm!r} rpm is not a valid target velocity")
        target_rpm = int(round(speed_rpm))
        self.write(OD_TARGET_VELOCITY, 0, target_rpm)
        return target_rpm

    def read_status(self) -> LoadStatus:
        state = self.state()
        speed_rpm = float(self.read(OD_VELOCITY_ACTUAL))
        torque_counts = int(self.read(OD_TORQUE_ACTUAL))
        return LoadStatus(state=state, speed_rpm=speed_rpm, torque_nm=torque_counts * self.torque_scale_nm)
