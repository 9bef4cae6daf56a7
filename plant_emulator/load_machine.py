"""Firmware of the emulated load machine (node 6): CiA 402 profile velocity.

Object dictionary: drivers/eds/load.eds. 0x60FF target velocity (rpm, mechanical) is followed through
a ramp and a PI speed loop (physics/mechanics.py) while OPERATION_ENABLED; otherwise the machine is
torque-free (the shaft coasts). The ramp: 0x6083 profile acceleration while the speed moves away from
standstill, 0x6084 profile deceleration while towards it (U32, rpm/s, rw); both start at the full rate,
the scenario's [load] ramp_rpm_per_s, read back on 0x2000 (ro), and a write of 0 or above the full rate
is refused (SDO abort 0x06090032 / 0x06090031). The fault reaction brakes at the full rate whatever they hold. 0x606C velocity actual (rpm), 0x6077 torque
actual in mNm (the load EDS has no rated torque; drivers.load_machine scales 0.001 Nm per count),
positive in the direction of rotation, i.e. negative while it brakes a motoring drive.

Heartbeat loss: FAULT_REACTION_ACTIVE, ramp to standstill with the speed loop still on, then FAULT.
"""

from __future__ import annotations

import math

from canopen.sdo import SdoAbortedError

from drivers.cia402 import State402

from . import physics as ph
from .cia402_device import ABORT_VALUE_TOO_HIGH, ABORT_VALUE_TOO_LOW, EMCY_HEARTBEAT, Cia402Device

MODE_PROFILE_VELOCITY = 3
RPM_TO_RAD_S = 2.0 * math.pi / 60.0
STANDSTILL_RPM = 1.0
OD_PROFILE_ACCELERATION = 0x6083  # U32, rpm/s
OD_PROFILE_DECELERATION = 0x6084  # U32, rpm/s


class LoadMachineFirmware(Cia402Device):
    mode_of_operation = MODE_PROFILE_VELOCITY

    def __init__(self, network, node_id: int, eds_path: str, ramp_rpm_per_s: float):
        super().__init__(network, node_id, eds_path)
        self.ramp_rpm_per_s = ramp_rpm_per_s
        self.speed_rpm = 0.0
        self.torque_nm = 0.0
        full_rpm_per_s = int(round(ramp_rpm_per_s))
        self.store(OD_PROFILE_ACCELERATION, 0, full_rpm_per_s)
        self.store(OD_PROFILE_DECELERATION, 0, full_rpm_per_s)

    def read_object(self, index: int, subindex: int):
        if index == 0x606C:
            return int(round(self.speed_rpm))
        if index == 0x6077:
            return int(max(-32768, min(32767, round(self.torque_nm * 1000.0))))
        if index == 0x2000:
            return int(round(self.ramp_rpm_per_s))
        return None

    def write_object(self, index: int, subindex: int, value) -> None:
        if index in (OD_PROFILE_ACCELERATION, OD_PROFILE_DECELERATION):
            if value < 1:
                raise SdoAbortedError(ABORT_VALUE_TOO_LOW)
            if value > round(self.ramp_rpm_per_s):
                raise SdoAbortedError(ABORT_VALUE_TOO_HIGH)

    def heartbeat_lost(self) -> None:
        if self.state == State402.OPERATION_ENABLED:
            self.error_code = EMCY_HEARTBEAT
            self.set_state(State402.FAULT_REACTION_ACTIVE)
            self.node.emcy.send(EMCY_HEARTBEAT, 0x11)
        else:
            self.fault(EMCY_HEARTBEAT)

    def chunk_setpoints(self, sp) -> None:
        with self.lock:
            # 0 ramps: the scenario's full rate (physics/mechanics.py)
            sp[ph.S_LOAD_ACCEL] = sp[ph.S_LOAD_DECEL] = 0.0
            if self.state == State402.FAULT_REACTION_ACTIVE:
                sp[ph.S_LOAD_ON] = 1.0
                sp[ph.S_LOAD_SPEED] = 0.0
            elif self.state == State402.OPERATION_ENABLED:
                sp[ph.S_LOAD_ON] = 1.0
                sp[ph.S_LOAD_SPEED] = float(self.stored(0x60FF)) * RPM_TO_RAD_S
                sp[ph.S_LOAD_ACCEL] = float(self.stored(OD_PROFILE_ACCELERATION)) * RPM_TO_RAD_S
                sp[ph.S_LOAD_DECEL] = float(self.stored(OD_PROFILE_DECELERATION)) * RPM_TO_RAD_S
            else:
                sp[ph.S_LOAD_ON] = 0.0
                sp[ph.S_LOAD_SPEED] = 0.0

    def publish(self, speed_rpm: float, torque_nm: float) -> None:
        self.speed_rpm = speed_rpm
        self.torque_nm = torque_nm
        with self.lock:
            if self.state == State402.FAULT_REACTION_ACTIVE and abs(speed_rpm) < STANDSTILL_RPM:
                self.set_state(State402.FAULT)
