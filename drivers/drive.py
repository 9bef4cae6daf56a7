"""The drive under test (inverter + PMSM) as seen from the service: CiA 402 profile torque plus the
manufacturer injection record 0x2000 (docs/interfaces.md).

Units are converted here and nowhere else: the service speaks newtons-metres, rpm, volts and radians;
the wire speaks per mille of the rated torque, mV and REAL32. Setpoints are checked before anything
goes out, so a refused value never reaches the bench half-applied.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

from drivers import DRIVE_EDS, lut_image
from drivers.canopen_bus import CanBus
from drivers.cia402 import State402
from drivers.cia402_master import Cia402Master
from drivers.errors import ConfigurationError, SdoError, SdoTimeoutError

MODE_PROFILE_TORQUE = 4

OD_VELOCITY_ACTUAL = 0x606C  # I32, rpm (mechanical)
OD_TARGET_TORQUE = 0x6071  # I16, per mille of rated torque
OD_RATED_TORQUE = 0x6076  # U32, mNm
OD_TORQUE_ACTUAL = 0x6077  # I16, per mille of rated torque
OD_RATED_CURRENT = 0x6075  # U32, mA
OD_CURRENT_ACTUAL = 0x6078  # I16, |i_dq| (the current vector's magnitude), per mille of rated current
ACTUALS_TPDO = 1  # TPDO1 (0x1800/0x1A00): torque, velocity and current actual, every 10 ms (docs/interfaces.md)
ACTUALS_OBJECTS = (OD_TORQUE_ACTUAL, OD_VELOCITY_ACTUAL, OD_CURRENT_ACTUAL)
OD_DC_LINK_VOLTAGE = 0x6079  # U32, mV
OD_INJECTION = 0x2000
SUB_HARMONIC_ORDER = 1  # U8
SUB_INJECTION_MODE = 2  # U8: 0 off, 1 manual, 2 LUT
SUB_THETA_COS = 3  # REAL32 rad, staged
SUB_THETA_SIN = 4  # REAL32 rad, staged
SUB_GAMMA_MAX = 5  # REAL32 rad
SUB_DECOUPLING = 6  # U8
SUB_COMMIT = 7  # U8: write 1 applies the staged pair; reads commits mod 256
OD_FURTHER_ORDERS = 0x2002  # order k at sub 3k-2 (U8, 0: unused), theta_cos / theta_sin at 3k-1 / 3k (REAL32 rad)
MAX_FURTHER_ORDERS = 3  # staged, applied by the next commit with the main order's theta
OD_LUT = 0x2001
SUB_LUT_DATA = 1  # DOMAIN
SUB_LUT_CRC = 2  # U32, CRC-32 of the LUT in force (lut_image.image_crc), 0: none
SUB_LUT_STATUS = 3  # U8, LUT_STATUSES
SUB_LUT_MAP_ID = 4  # U32, map id of the LUT in force (from the image header), 0: none
# 0x2001:3; after a refused download the LUT before it stays in force (its map id and CRC still read)
LUT_STATUSES = {0: "none", 1: "in_force", 2: "last_download_refused"}
OD_VOLTAGE_REFERENCE = 0x2010
SUB_UD_REF = 1  # REAL32 V
SUB_UQ_REF = 2  # REAL32 V

INJECTION_OFF = 0
INJECTION_MANUAL = 1
INJECTION_LUT = 2
INJECTION_MODES = {"off": INJECTION_OFF, "manual": INJECTION_MANUAL, "lut": INJECTION_LUT}

# writes the drive applies as a new setpoint, each toggling the DAQ sync line once (docs/interfaces.md)
SETPOINT_OBJECTS = frozenset(
    {
        (OD_TARGET_TORQUE, 0),
        (OD_INJECTION, SUB_HARMONIC_ORDER),
        (OD_INJECTION, SUB_INJECTION_MODE),
        (OD_INJECTION, SUB_DECOUPLING),
        (OD_INJECTION, SUB_COMMIT),
    }
)

PER_MILLE = 1000.0


@dataclass(frozen=True)
class DriveStatus:
    """One snapshot of the drive, in SI-ish units (read by SDO, one object after the other)."""

    state: State402
    torque_nm: float
    speed_rpm: float
    udc_v: float
    ud_ref_v: float
    uq_ref_v: float


@dataclass(frozen=True)
class DriveActuals:
    """One TPDO of the drive's actuals (ACTUALS_TPDO), in SI-ish units."""

    torque_nm: float  # torque actual 0x6077 (the drive's estimate from its measured currents)
    speed_rpm: float  # velocity actual 0x606C, mechanical
    current_a: float  # current actual 0x6078, |i_dq|, A (peak phase current)
    received_at: float  # time.monotonic() of its arrival here


@dataclass(frozen=True)
class LutInForce:
    """Which LUT the drive holds, as it reports it (0x2001:4, :2, :3)."""

    map_id: int  # 0: no LUT
    crc32: int  # lut_image.image_crc of the image in force, 0: no LUT
    status: str  # LUT_STATUSES


class DriveClient(Cia402Master):
    """CANopen client of the drive under test (default node 5), SDO only.

    connect() reads the rated torque (0x6076) once; torque setpoints and readings are scaled with it.
    Every setpoint the drive applies toggles the DAQ sync flag once. `setpoints_written` counts the
    accepted writes to those objects (SETPOINT_OBJECTS), so the caller can tell, by comparing with the
    toggles it has seen on the DAQ, the exact sample at which its last setpoint took effect.
    """

    device_kind = "drive"

    def __init__(self, bus: CanBus, node_id: int, sdo_timeout_s: float = 0.5):
        super().__init__(bus, node_id, DRIVE_EDS, MODE_PROFILE_TORQUE, sdo_timeout_s)
        self.rated_torque_nm: float | None = None
        self.setpoints_written = 0
        self.commits_expected: int | None = None  # the drive's commit counter as we expect it (mod 256)
        # told the running number of every setpoint accepted (the service times its sync toggle)
        self.on_setpoint: Callable[[int], None] | None = None
        self.rated_current_a: float | None = None
        # told every TPDO of the actuals, from the CAN receive thread: must be quick, never an SDO
        self.on_actuals: Callable[[DriveActuals], None] | None = None
        self.actuals: DriveActuals | None = None  # the latest
        # the further orders last written to 0x2002 (None: unknown, all written at the next set_injection)
        self._further_written: tuple[tuple[int, float, float], ...] | None = None

    def write(self, index: int, subindex: int, value) -> None:
        try:
            super().write(index, subindex, value)
        except SdoTimeoutError:
            # the request may have reached the drive and only the answer be late: for a commit the
            # counter tells (0x2000:7 read-back), so the sync-toggle count stays exact
            if (index, subindex) == (OD_INJECTION, SUB_COMMIT) and self._commit_went_through():
                self._count_setpoint()
            raise
        if (index, subindex) in SETPOINT_OBJECTS:
            self._count_setpoint()
        if (index, subindex) == (OD_INJECTION, SUB_COMMIT) and self.commits_expected is not None:
            self.commits_expected = (self.commits_expected + 1) & 0xFF

    def _count_setpoint(self) -> None:
        self.setpoints_written += 1
        if self.on_setpoint is not None:
            self.on_setpoint(self.setpoints_written)

    def _commit_went_through(self) -> bool:
        if self.commits_expected is None:
            return False
        try:
            reported = self.commit_count()
        except SdoError:
            return False
        went = reported == (self.commits_expected + 1) & 0xFF
        self.commits_expected = reported
        return went

    def resync_setpoint_count(self, toggles_seen: int) -> dict:
        """Re-establish the setpoint/sync-toggle accounting after any error: read back the drive's
        commit counter (0x2000:7, commits mod 256) as the base for the next commits, and set
        `setpoints_written` to the toggles the caller has seen on the DAQ once the drive has no
        setpoint pending (the caller's job: the drive applies one per DAQ chunk). Returns what was
        corrected, for the log: {"commits_reported", "commits_expected", "setpoints_written_before"}."""
        reported = self.commit_count()
        report = {
            "commits_reported": reported,
            "commits_expected": self.commits_expected,
            "setpoints_written_before": self.setpoints_written,
            "toggles_seen": toggles_seen,
        }
        self.commits_expected = reported
        self.setpoints_written = toggles_seen
        return report

    def _after_connect(self) -> None:
        self._further_written = None  # another master may have written 0x2002 meanwhile
        rated_mnm = int(self.read(OD_RATED_TORQUE))
        if rated_mnm <= 0:
            raise ConfigurationError(
                f"drive node {self.node_id}: motor rated torque 0x6076 is {rated_mnm} mNm; "
                "cannot scale torque setpoints"
            )
        self.rated_torque_nm = rated_mnm / 1000.0
        rated_ma = int(self.read(OD_RATED_CURRENT))
        if rated_ma <= 0:
            raise ConfigurationError(
                f"drive node {self.node_id}: motor rated current 0x6075 is {rated_ma} mA; cannot scale current actual"
            )
        self.rated_current_a = rated_ma / 1000.0
        self._subscribe_actuals()

    def _subscribe_actuals(self) -> None:
        """Listen to the TPDO of the actuals, mapped as the EDS says (the drive sends it cyclically once
        NMT OPERATIONAL); a mapping without torque, velocity and current actual is a configuration error."""
        self.node.tpdo.read(from_od=True)  # subscribes the enabled maps on the network
        tpdo = self.node.tpdo[ACTUALS_TPDO]
        mapped = {var.index for var in tpdo.map}
        if not tpdo.enabled or not set(ACTUALS_OBJECTS) <= mapped:
            raise ConfigurationError(
                f"drive node {self.node_id}: TPDO{ACTUALS_TPDO} must be enabled and map torque, velocity and "
                f"current actual (0x6077, 0x606C, 0x6078); its EDS maps {sorted(hex(i) for i in mapped)}"
            )
        tpdo.add_callback(self._on_actuals_pdo)

    def actuals_mapping(self) -> tuple[list[int], list[int]]:
        """(the device's, the EDS's) mapping entries of the actuals TPDO (0x1A00 + n - 1: index << 16 | sub << 8 |
        bits each), the device's read by SDO: the bring-up check compares them."""
        index = 0x1A00 + ACTUALS_TPDO - 1
        device = [int(self.read(index, k)) for k in range(1, int(self.read(index, 0)) + 1)]
        eds = self.node.object_dictionary[index]
        count = int(eds[0].default or 0)  # type: ignore[index]
        return device, [int(eds[k].default or 0) for k in range(1, count + 1)]  # type: ignore[index]

    def _on_actuals_pdo(self, pdo_map) -> None:
        values = {var.index: var.raw for var in pdo_map.map}
        actuals = DriveActuals(
            torque_nm=int(values[OD_TORQUE_ACTUAL]) / PER_MILLE * self.rated_torque_nm,
            speed_rpm=float(values[OD_VELOCITY_ACTUAL]),
            current_a=int(values[OD_CURRENT_ACTUAL]) / PER_MILLE * self.rated_current_a,
            received_at=time.monotonic(),
        )
        self.actuals = actuals
        if self.on_actuals is not None:
            self.on_actuals(actuals)

    def close(self) -> None:
        network = self._network
        if network is not None:
            for pdo_map in self.node.tpdo.map.values():
                if pdo_map.cob_id is not None:
                    try:
                        network.unsubscribe(pdo_map.cob_id, pdo_map.on_message)
                    except (KeyError, ValueError):
                        pass
        super().close()

    def _safe_steps(self):
        return [("target torque 0", lambda: self.write(OD_TARGET_TORQUE, 0, 0)), ("injection off", self.injection_off)]

    # -- setpoints ----------------------------------------------------------------------------------
    def _rated_nm(self) -> float:
        self._require_connected()
        assert self.rated_torque_nm is not None
        return self.rated_torque_nm

    def torque_to_per_mille(self, torque_nm: float) -> int:
        """Wire value of a torque setpoint; ValueError outside +-rated torque (nothing is sent)."""
        rated_nm = self._rated_nm()
        if not math.isfinite(torque_nm) or abs(torque_nm) > rated_nm * (1.0 + 1e-9):
            raise ValueError(
                f"torque {torque_nm!r} Nm outside the drive's range +-{rated_nm:g} Nm (motor rated torque, 0x6076)"
            )
        return max(-1000, min(1000, round(torque_nm / rated_nm * PER_MILLE)))

    def set_torque_nm(self, torque_nm: float) -> int:
        """Target torque 0x6071 in per mille of the rated torque. Returns the per-mille value sent."""
        per_mille = self.torque_to_per_mille(torque_nm)
        self.write(OD_TARGET_TORQUE, 0, per_mille)
        return per_mille

    def torque_actual_nm(self) -> float:
        """The drive's torque actual 0x6077 (its estimate from the measured currents), Nm."""
        return int(self.read(OD_TORQUE_ACTUAL)) / PER_MILLE * self._rated_nm()

    def set_injection(
        self, theta_cos_rad: float, theta_sin_rad: float, further: tuple[tuple[int, float, float], ...] = ()
    ) -> int:
        """Stage theta = [theta_cos, theta_sin] (REAL32, rad) of the main order (0x2000:1) and the further
        orders `further` ((order, theta_cos_rad, theta_sin_rad), up to 3, 0x2002), and commit, so that the
        drive applies them all atomically at its next control period: v_inj is their sum (eq. 3, 12), the
        voltage rotated once by it. Exactly one setpoint (one sync toggle); the injection mode is set
        separately with set_injection_mode. 0x2002 is written only where it changed. Returns 1."""
        for name, value in (("theta_cos_rad", theta_cos_rad), ("theta_sin_rad", theta_sin_rad)):
            if not math.isfinite(value):
                raise ValueError(f"{name} must be finite, got {value!r}")
        staged = self._further_slots(further)
        self._require_connected()
        self._stage_further(staged)
        self.write(OD_INJECTION, SUB_THETA_COS, float(theta_cos_rad))
        self.write(OD_INJECTION, SUB_THETA_SIN, float(theta_sin_rad))
        self.write(OD_INJECTION, SUB_COMMIT, 1)
        return 1

    @staticmethod
    def _further_slots(further: tuple[tuple[int, float, float], ...]) -> tuple[tuple[int, float, float], ...]:
        """The 3 slots of 0x2002 for `further` (unused slots order 0); ValueError naming what is wrong."""
        if len(further) > MAX_FURTHER_ORDERS:
            raise ValueError(f"at most {MAX_FURTHER_ORDERS} further orders, got {len(further)}")
        slots = []
        for order, c, s in further:
            if isinstance(order, bool) or int(order) != order or not 1 <= int(order) <= 255:
                raise ValueError(f"a further order must be an integer 1..255, got {order!r}")
            if not (math.isfinite(c) and math.isfinite(s)):
                raise ValueError(f"theta of order {order} must be finite, got ({c!r}, {s!r})")
            slots.append((int(order), float(c), float(s)))
        if len({h for h, _, _ in slots}) != len(slots):
            raise ValueError(f"further orders given twice: {[h for h, _, _ in slots]}")
        return tuple(slots) + ((0, 0.0, 0.0),) * (MAX_FURTHER_ORDERS - len(slots))

    def _stage_further(self, slots: tuple[tuple[int, float, float], ...]) -> None:
        before = self._further_written
        self._further_written = None  # unknown until every write below went through
        for k, slot in enumerate(slots):
            if before is not None and before[k] == slot:
                continue
            for sub, value in zip((3 * k + 1, 3 * k + 2, 3 * k + 3), slot):
                self.write(OD_FURTHER_ORDERS, sub, value)
        self._further_written = slots

    def injection_off(self) -> None:
        """Injection mode 0 (off); always written, it is part of the safety path."""
        self.write(OD_INJECTION, SUB_INJECTION_MODE, INJECTION_OFF)

    def set_injection_mode(self, mode: int | str) -> None:
        """Injection mode 0x2000:2: "off"/0, "manual"/1 (theta from 0x2000:3/4), "lut"/2."""
        mode = INJECTION_MODES.get(mode, mode) if isinstance(mode, str) else mode
        if mode not in (INJECTION_OFF, INJECTION_MANUAL, INJECTION_LUT):
            raise ValueError(f"injection mode must be off/manual/lut (0/1/2), got {mode!r}")
        self.write(OD_INJECTION, SUB_INJECTION_MODE, mode)

    def injection_mode(self) -> int:
        return int(self.read(OD_INJECTION, SUB_INJECTION_MODE))

    def commit_count(self) -> int:
        """Number of theta commits the drive has applied, modulo 256 (0x2000:7 read-back)."""
        return int(self.read(OD_INJECTION, SUB_COMMIT))

    def set_harmonic_order(self, h: int) -> None:
        """Harmonic order h of the injection (0x2000:1, U8)."""
        if isinstance(h, bool) or int(h) != h or not 1 <= int(h) <= 255:
            raise ValueError(f"harmonic order must be an integer 1..255, got {h!r}")
        self.write(OD_INJECTION, SUB_HARMONIC_ORDER, int(h))

    def harmonic_order(self) -> int:
        return int(self.read(OD_INJECTION, SUB_HARMONIC_ORDER))

    def set_gamma_max_rad(self, gamma_max_rad: float) -> None:
        """Injection amplitude limit (0x2000:5, REAL32 rad); the drive clamps |theta| to it."""
        if not math.isfinite(gamma_max_rad) or not 0.0 < gamma_max_rad <= math.pi:
            raise ValueError(f"gamma_max_rad must be in (0, pi], got {gamma_max_rad!r}")
        self.write(OD_INJECTION, SUB_GAMMA_MAX, float(gamma_max_rad))

    def gamma_max_rad(self) -> float:
        return float(self.read(OD_INJECTION, SUB_GAMMA_MAX))

    def set_decoupling(self, on: bool) -> None:
        """Decoupling of the current controller (0x2000:6, paper sec. 3.1)."""
        self.write(OD_INJECTION, SUB_DECOUPLING, 1 if on else 0)

    # -- LUT download -------------------------------------------------------------------------------
    def download_lut(self, blob: bytes) -> LutInForce:
        """Download a LUT image (drivers/lut_image.py) to 0x2001:1 (segmented SDO), then read back what
        the drive holds and check its CRC against the image's own (lut_image.image_crc: CRC-32 of the
        image without its CRC field). Returns the drive's report. A malformed image is the drive's to
        refuse (SDO abort 0x08000020)."""
        if not blob:
            raise ValueError("LUT image is empty")
        self.download_domain(OD_LUT, SUB_LUT_DATA, blob)
        expected = lut_image.image_crc(blob)
        held = self.lut_in_force()
        if held.crc32 != expected:
            raise SdoError(
                self.node_id,
                "read",
                OD_LUT,
                SUB_LUT_CRC,
                self._object_name(OD_LUT, SUB_LUT_CRC),
                f"LUT CRC-32 read-back {lut_image.crc_hex(held.crc32)} != {lut_image.crc_hex(expected)} "
                f"of the {len(blob)} bytes sent (LUT status {held.status})",
            )
        return held

    def lut_in_force(self) -> LutInForce:
        """Three expedited SDO reads: map id, CRC and status of the drive's LUT."""
        code = int(self.read(OD_LUT, SUB_LUT_STATUS))
        return LutInForce(
            map_id=int(self.read(OD_LUT, SUB_LUT_MAP_ID)),
            crc32=int(self.read(OD_LUT, SUB_LUT_CRC)),
            status=LUT_STATUSES.get(code, f"unknown ({code})"),
        )

    # -- readings -----------------------------------------------------------------------------------
    def read_status(self) -> DriveStatus:
        state = self.state()
        torque_nm = self.torque_actual_nm()
        speed_rpm = float(self.read(OD_VELOCITY_ACTUAL))
        udc_mv = int(self.read(OD_DC_LINK_VOLTAGE))
        ud_ref_v = float(self.read(OD_VOLTAGE_REFERENCE, SUB_UD_REF))
        uq_ref_v = float(self.read(OD_VOLTAGE_REFERENCE, SUB_UQ_REF))
        return DriveStatus(
            state=state,
            torque_nm=torque_nm,
            speed_rpm=speed_rpm,
            udc_v=udc_mv / 1000.0,
            ud_ref_v=ud_ref_v,
            uq_ref_v=uq_ref_v,
        )
