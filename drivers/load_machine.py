"""The load machine that holds the bench speed: CiA 402 profile velocity (docs/interfaces.md).

Shares all CiA 402 master logic with the drive (drivers.cia402_master); only the mode, the speed
setpoint, its ramp and its safety steps (the full ramp back and speed 0 before the power stage goes
off) are its own.

The ramp: 0x6083 profile acceleration (away from standstill) and 0x6084 profile deceleration (towards
it), U32 in rpm/s; both start at the load's full rate (0x2000, ro). A run-up sets a slow one
(`set_ramp_rpm_per_s`); a stop must not inherit it: `brake_to_standstill()` puts the full rate back
before it commands 0 rpm, and `disable()` does the same, so every run after it starts at the full rate
(connect reads the ramp: one left slow is restored by the first of them). Without a slow ramp in
force, neither sends anything more than before.
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
OD_PROFILE_ACCELERATION = 0x6083  # U32, rpm/s
OD_PROFILE_DECELERATION = 0x6084  # U32, rpm/s
OD_FULL_RAMP = 0x2000  # U32 ro, rpm/s: the load's full rate, the default of both

INT32_MAX = 2**31 - 1
UINT32_MAX = 2**32 - 1


@dataclass(frozen=True)
class LoadStatus:
    state: State402
    speed_rpm: float
    torque_nm: float


@dataclass(frozen=True)
class LoadRamp:
    """The load's ramp as it reads back, rpm/s."""

    acceleration_rpm_per_s: int  # 0x6083: while the speed moves away from standstill
    deceleration_rpm_per_s: int  # 0x6084: while it moves towards standstill
    full_rpm_per_s: int  # 0x2000: the load's full rate (the default, and what a stop brakes at)


class LoadClient(Cia402Master):
    """CANopen client of the load machine (default node 6), SDO only.

    torque_scale_nm: newton-metres per count of the load's 0x6077 (the load EDS has no rated-torque
    object; 0.001 reads the value as mNm).
    """

    device_kind = "load machine"

    def __init__(self, bus: CanBus, node_id: int, sdo_timeout_s: float = 0.5, torque_scale_nm: float = 0.001):
        super().__init__(bus, node_id, LOAD_EDS, MODE_PROFILE_VELOCITY, sdo_timeout_s)
        self.torque_scale_nm = torque_scale_nm
        self.full_ramp_rpm_per_s = 0  # 0x2000, read at connect
        self._ramp_slowed = False  # a ramp below the full rate may be in force (set by this client)

    def _after_connect(self) -> None:
        # read only (the device is left as found until the bench is whole); a slow ramp left in force
        # (a service that died mid run-up) is put back to the full rate by the first stop or disable
        ramp = self.read_ramp()
        self.full_ramp_rpm_per_s = ramp.full_rpm_per_s
        self._ramp_slowed = ramp != LoadRamp(ramp.full_rpm_per_s, ramp.full_rpm_per_s, ramp.full_rpm_per_s)

    def _safe_steps(self):
        return [
            ("full ramp", self._restore_full_ramp_if_slowed),
            ("target velocity 0", lambda: self.write(OD_TARGET_VELOCITY, 0, 0)),
        ]

    def set_ramp_rpm_per_s(self, rate_rpm_per_s: float) -> int:
        """Profile acceleration and deceleration (0x6083, 0x6084) both to this rate, rpm/s (integer on
        the wire; the load refuses more than its full rate, 0x2000). Returns the value sent."""
        if not math.isfinite(rate_rpm_per_s) or rate_rpm_per_s <= 0:
            raise ValueError(f"ramp {rate_rpm_per_s!r} rpm/s is not valid: it must be a positive finite rate")
        rate = int(round(rate_rpm_per_s))
        if not 1 <= rate <= UINT32_MAX:
            raise ValueError(f"ramp {rate_rpm_per_s!r} rpm/s is outside 1..{UINT32_MAX} rpm/s (an integer on the wire)")
        self._ramp_slowed = True  # also if a write fails half-way: the next stop restores the full rate
        self.write(OD_PROFILE_ACCELERATION, 0, rate)
        self.write(OD_PROFILE_DECELERATION, 0, rate)
        self._ramp_slowed = rate != self.full_ramp_rpm_per_s
        return rate

    def read_ramp(self) -> LoadRamp:
        """The ramp as the load reads it back."""
        return LoadRamp(
            acceleration_rpm_per_s=int(self.read(OD_PROFILE_ACCELERATION)),
            deceleration_rpm_per_s=int(self.read(OD_PROFILE_DECELERATION)),
            full_rpm_per_s=int(self.read(OD_FULL_RAMP)),
        )

    def restore_full_ramp(self) -> int:
        """Profile acceleration and deceleration back to the load's full rate. Returns it."""
        self.write(OD_PROFILE_DECELERATION, 0, self.full_ramp_rpm_per_s)  # the one a stop brakes with, first
        self.write(OD_PROFILE_ACCELERATION, 0, self.full_ramp_rpm_per_s)
        self._ramp_slowed = False
        return self.full_ramp_rpm_per_s

    def _restore_full_ramp_if_slowed(self) -> None:
        # no SDO on a stop unless a slow ramp was set: a stop stays as quick as before run-ups
        if self._ramp_slowed:
            self.restore_full_ramp()

    def brake_to_standstill(self) -> None:
        """The stop a slow ramp must not slow: the full ramp back (only if a slower one was set), then
        target velocity 0, the load left enabled to brake on its speed loop (disable it at standstill: a
        disabled load coasts). Both steps are tried (0 rpm even if the ramp write failed); the first
        error is raised."""
        errors: list[BaseException] = []
        for step in (self._restore_full_ramp_if_slowed, lambda: self.set_speed_rpm(0.0)):
            try:
                step()
            except Exception as exc:  # noqa: BLE001 - the speed 0 is sent whatever the ramp write said
                errors.append(exc)
        if errors:
            raise errors[0]

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
