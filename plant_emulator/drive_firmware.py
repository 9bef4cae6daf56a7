"""Firmware of the emulated drive (node 5): CiA 402 profile torque + harmonic injection record.

Object dictionary: drivers/eds/drive.eds, semantics: docs/interfaces.md. The fast control loop
(current control, injection, delay) is in physics/firmware.py; this module is the slow firmware around it:
it validates SDO writes, stages setpoints, and hands them to the control loop at a piece boundary
(a 256-sample chunk when the plant runs as fast as the DAQ is read; in paced mode a piece of a few ms,
cut where the setpoint was written: `setpoint_written` wakes the plant thread on every event).

Further injection orders (0x2002, up to 3: order and theta each) are staged and applied with the next
commit (0x2000:7), with the main order's theta, as one event: in manual mode the control loop injects
the sum of every order's angle (physics/firmware.py), every theta scaled by one factor so that the sum of
their |theta| is at most gamma_max.

Setpoint application and the DAQ sync line: every accepted write of target torque (0x6071), theta
commit (0x2000:7), injection mode (0x2000:2), harmonic order (0x2000:1), decoupling (0x2000:6) or
voltage estimate (0x2000:8, eq. 11) becomes one event. At each piece start the control loop takes at most ONE event, applies it from the
piece's first sample on and toggles the sync level there, so each event is exactly one visible
toggle (two at the same sample would cancel). gamma_max (0x2000:5) takes effect at the next piece
without a toggle: it only clamps |theta|.

LUT (0x2001): a download is decoded and checked (drivers.lut_image.decode, docs/interfaces.md "LUT image");
a bad image is refused with SDO abort 0x08000020 and the LUT in force stays (status 2 = last
download refused). 0x2001:2 and :4 report the CRC (lut_image.image_crc) and the map id of the LUT in
force (0 without one). The drive takes format_version 2 to 7 images (a version 2 image: its valid
cells as flag 1, cartesian interpolation; version 4 adds flag 3, injection off; 5 and 6 integer cells; 7 per-row
speed breakpoints, its cells not stored derived along their row at decode). In injection mode 2 the control loop's
chunk-rate task takes theta at the shaft's speed from `theta_schedule` (so it follows a run-up within a piece, as a
drive's torque task does): theta interpolated by the image's own mode (`Lut.theta`: cartesian
theta or polar gamma/delta along the shortest arc, by position on the non-uniform axes) in (torque
command, measured speed, measured U_dc), clamped at the axis ends; entries at flag 1 (ok) and 2
(filled) cells, nothing at flag 0, and exactly nothing (theta 0) wherever a corner of non-zero weight
is at flag 3 (injection off: never worse than no compensation); then |theta| clamped to gamma_max; the injection runs at the LUT's
harmonic order.

Actuals (TPDO1, 0x1800/0x1A00 of the EDS): torque actual 0x6077, velocity actual 0x606C and current actual
0x6078 (|i_dq|, the current vector's magnitude, per mille of the rated current 0x6075), sent every event
timer period (0x1800:5, 10 ms) while the node is NMT OPERATIONAL, as a drive's cyclic actuals are: the
service's actuals interlock trips on them within a control period of the bus.

Safety: power (torque, injection) only in OPERATION_ENABLED with U_dc >= udc_min_v; heartbeat loss
-> FAULT, EMCY 0x8130, target torque 0 and injection mode off (applied at once, without toggles:
this is the drive's reaction, not a service setpoint).
"""

from __future__ import annotations

import logging
import math
import threading
from collections import deque

import numpy as np
from canopen.sdo import SdoAbortedError

from drivers import lut_image
from drivers.cia402 import State402
from drivers.injection_limit import injection_scale

from . import physics as ph
from .cia402_device import ABORT_VALUE_RANGE, Cia402Device

ABORT_CANNOT_STORE = 0x08000020  # data cannot be transferred or stored to the application

log = logging.getLogger(__name__)

MODE_PROFILE_TORQUE = 4
INJ_OFF, INJ_MANUAL, INJ_LUT = 0, 1, 2
PER_MILLE = 1000.0
RPM_TO_RAD_S = 2.0 * math.pi / 60.0
# LUT mode's speed schedule for a piece: theta linear between 1-rpm points misses Lut.theta by less than
# 0.2 % of |theta| where theta* turns 6.5 deg/rpm (a chord of a 6.5 deg arc), -54 dB: far under any target
SCHEDULE_STEP_RPM = 1.0
SCHEDULE_MAX_ROWS = 8192  # a 0..8000 rpm axis at 1 rpm; wider axes at a coarser step
MAX_HARMONIC_ORDER = 255


class DriveFirmware(Cia402Device):
    mode_of_operation = MODE_PROFILE_TORQUE

    def __init__(self, network, node_id: int, eds_path: str, udc_min_v: float = 6.0):
        super().__init__(network, node_id, eds_path)
        od = self.node.object_dictionary
        self.rated_torque_nm = int(od[0x6076].default) / 1000.0
        self.rated_current_a = int(od[0x6075].default) / 1000.0
        self.node.tpdo.read(from_od=True)  # TPDO1: the actuals, mapped as the EDS says
        self.udc_min_v = udc_min_v
        # setpoints in force in the control loop
        self.torque_nm = 0.0
        self.inj_mode = int(od[0x2000][2].default)
        self.harmonic_order = int(od[0x2000][1].default)
        self.theta = (0.0, 0.0)
        # further injection orders in force (0x2002, committed with 0x2000:7): ((h_k, theta_cos, theta_sin), ...)
        self.further: tuple[tuple[int, float, float], ...] = ()
        self.gamma_max_rad = float(od[0x2000][5].default)
        self.decoupling = int(od[0x2000][6].default)
        self.voltage_estimate = int(od[0x2000][8].default)
        self.sync_level = 0
        self.commit_count = 0
        self.events_applied = 0
        self._events: deque[tuple[str, object]] = deque()
        self.setpoint_written = threading.Event()  # set with every event: wakes the paced plant thread
        # LUT in force (None: no LUT)
        self.lut: lut_image.Lut | None = None
        self.lut_blob = b""
        self.lut_status = 0
        self.lut_refused = 0
        self._schedule_key: tuple | None = None  # theta_schedule's inputs and result, made again on a change
        self._schedule = ph.NO_THETA_SCHEDULE
        # measurements published by the control loop
        self.speed_rpm = 0.0
        self.torque_actual_nm = 0.0
        self.current_a = 0.0
        self.udc_v = 0.0
        self.ud_ref_v = 0.0
        self.uq_ref_v = 0.0

    # -- SDO ---------------------------------------------------------------------------------------
    def read_object(self, index: int, subindex: int):
        if index == 0x6077:
            return int(np.clip(round(self.torque_actual_nm / self.rated_torque_nm * PER_MILLE), -32768, 32767))
        if index == 0x606C:
            return int(round(self.speed_rpm))
        if index == 0x6078:
            return self._current_per_mille()
        if index == 0x6079:
            return int(max(0.0, round(self.udc_v * 1000.0)))
        if index == 0x2010:
            if subindex == 1:
                return float(self.ud_ref_v)
            if subindex == 2:
                return float(self.uq_ref_v)
        if index == 0x2000 and subindex == 7:
            return self.commit_count & 0xFF
        if index == 0x2001:
            if subindex == 2:
                return self.lut.crc if self.lut is not None else 0
            if subindex == 3:
                return self.lut_status
            if subindex == 4:
                return self.lut.map_id if self.lut is not None else 0
        return None

    def write_object(self, index: int, subindex: int, value) -> None:
        if index == 0x6071:
            if abs(int(value)) > 1000:
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            self._queue_event("torque", int(value) / PER_MILLE * self.rated_torque_nm)
        elif index == 0x2000:
            self._write_injection(subindex, value)
        elif index == 0x2002:
            self._write_further(subindex, value)
        elif index == 0x2001 and subindex == 1:
            blob = bytes(value)
            try:
                lut = lut_image.decode(blob)
            except lut_image.LutImageError as exc:
                log.warning("drive: LUT download refused: %s", exc)
                self.lut_status = 2
                self.lut_refused += 1
                raise SdoAbortedError(ABORT_CANNOT_STORE) from None
            self.lut = lut
            self.lut_blob = blob
            self.lut_status = 1
            log.info(
                "drive: LUT of map %d in force (format_version %d, orders %s, %s interpolation, %d ok and %d filled "
                "entries, %d off of %d cells)",
                lut.map_id,
                lut.format_version,
                list(lut.orders),
                lut.interpolation,
                int(lut.valid.sum()),
                int(lut.filled.sum()),
                int(lut.injection_off.sum()),
                lut.flags.size,
            )

    def _write_injection(self, subindex: int, value) -> None:
        if subindex == 1:
            if not 1 <= int(value) <= MAX_HARMONIC_ORDER:
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            self._queue_event("harmonic_order", int(value))
        elif subindex == 2:
            if int(value) not in (INJ_OFF, INJ_MANUAL, INJ_LUT):
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            self._queue_event("inj_mode", int(value))
        elif subindex in (3, 4):
            if not math.isfinite(float(value)) or abs(float(value)) > math.pi:
                raise SdoAbortedError(ABORT_VALUE_RANGE)
        elif subindex == 5:
            g = float(value)
            if not (math.isfinite(g) and 0.0 <= g <= math.pi):
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            self.gamma_max_rad = g
        elif subindex == 6:
            if int(value) not in (0, 1):
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            self._queue_event("decoupling", int(value))
        elif subindex == 8:
            if int(value) not in (0, 1):
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            self._queue_event("voltage_estimate", int(value))
        elif subindex == 7:
            if int(value) == 1:
                staged = (float(self.stored(0x2000, 3)), float(self.stored(0x2000, 4)))
                self._queue_event("theta", (staged, self._staged_further()))
                self.commit_count += 1
            elif int(value) != 0:
                raise SdoAbortedError(ABORT_VALUE_RANGE)

    def _write_further(self, subindex: int, value) -> None:
        """0x2002: order k at sub 3k-2 (0: unused), its theta_cos and theta_sin at 3k-1 and 3k; staged until
        the next commit (0x2000:7) applies them with the main order's theta, as one setpoint."""
        if not 1 <= subindex <= 3 * (ph.MAX_INJECTION_ORDERS - 1):
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        if subindex % 3 == 1:
            if not 0 <= int(value) <= MAX_HARMONIC_ORDER:
                raise SdoAbortedError(ABORT_VALUE_RANGE)
        elif not math.isfinite(float(value)) or abs(float(value)) > math.pi:
            raise SdoAbortedError(ABORT_VALUE_RANGE)

    def _staged_further(self) -> tuple[tuple[int, float, float], ...]:
        """The further orders staged in 0x2002 (those with an order); refused (value range) when an order is
        given twice or is the main order (0x2000:1): one theta per order."""
        further = []
        for k in range(ph.MAX_INJECTION_ORDERS - 1):
            order = int(self.stored(0x2002, 3 * k + 1))
            if order:
                further.append((order, float(self.stored(0x2002, 3 * k + 2)), float(self.stored(0x2002, 3 * k + 3))))
        orders = [int(self.stored(0x2000, 1))] + [h for h, _, _ in further]
        if len(set(orders)) != len(orders):
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        return tuple(further)

    def _queue_event(self, kind: str, value) -> None:
        self._events.append((kind, value))
        self.setpoint_written.set()

    # -- state machine hooks -----------------------------------------------------------------------
    def state_changed(self, old: State402, new: State402) -> None:
        if new == State402.FAULT:
            self._events.clear()
            self.torque_nm = 0.0
            self.inj_mode = INJ_OFF
            self.store(0x6071, 0, 0)
            self.store(0x2000, 2, INJ_OFF)

    # -- control loop interface (physics thread) ---------------------------------------------------
    def effective_theta(self) -> tuple[float, float]:
        """Theta of the main order the control loop uses: mode manual: the committed pair; mode LUT: the
        LUT interpolated by its own mode at (torque command, measured speed, measured U_dc)
        (drivers.lut_image.Lut.theta); off (or LUT mode without a LUT): zero. Clamped with the further
        orders (`effective_further`) so that the sum of their |theta| is at most gamma_max."""
        if self.inj_mode == INJ_MANUAL:
            c, s = self.theta
        elif self.inj_mode == INJ_LUT and self.lut is not None:
            c, s = self.lut.theta(self.torque_nm, self.speed_rpm, self.udc_v)
        else:
            return 0.0, 0.0
        return self._clamped(c, s, self._further_unscaled(self.speed_rpm))

    def _further_unscaled(self, speed_rpm: float) -> tuple[tuple[int, float, float], ...]:
        """The further orders in force before the common scale: mode manual: 0x2002 as committed; mode LUT: each
        further order's own LUT of a several-order image (version 8) at the operating point, `speed_rpm`
        (drivers.lut_image.Lut.further); else none."""
        if self.inj_mode == INJ_MANUAL:
            return self.further
        if self.inj_mode == INJ_LUT and self.lut is not None:
            return tuple(
                (lut.harmonic_order, *lut.theta(self.torque_nm, speed_rpm, self.udc_v)) for lut in self.lut.further
            )
        return ()

    def effective_further(self) -> tuple[tuple[int, float, float], ...]:
        """The further orders the control loop injects (manual: 0x2002; LUT: the image's further orders), each
        theta scaled by the same factor as the main order's (`_scale`)."""
        further = self._further_unscaled(self.speed_rpm)
        if self.inj_mode == INJ_LUT and self.lut is not None:
            main = self.lut.theta(self.torque_nm, self.speed_rpm, self.udc_v)
        else:
            main = self.theta
        k = self._scale(*main, further)
        return tuple((h, c * k, s * k) for h, c, s in further)

    def _scale(self, c: float, s: float, further: tuple[tuple[int, float, float], ...] = ()) -> float:
        """The factor on every order's theta that keeps |v_inj| <= gamma_max (0x2000:5) at every angle:
        the sum of the orders' |theta| (the main order's (c, s) and the further orders in force) clamped to
        gamma_max; with one order that is |theta| <= gamma_max."""
        return injection_scale([math.hypot(c, s), *(math.hypot(fc, fs) for _, fc, fs in further)], self.gamma_max_rad)

    def _clamped(self, c: float, s: float, further: tuple[tuple[int, float, float], ...] = ()) -> tuple[float, float]:
        """theta of the main order scaled by `_scale`, as the control loop takes it."""
        k = self._scale(c, s, further)
        return c * k, s * k

    def theta_schedule(self) -> np.ndarray:
        """LUT mode: theta against the shaft's speed over the LUT's speed axis at the torque command, U_dc and
        gamma_max in force, every SCHEDULE_STEP_RPM at most, each point `effective_theta`'s (Lut.theta, clamped
        to gamma_max; beyond the axis ends Lut.theta holds the end's value, as the schedule does): the control
        loop's chunk-rate task interpolates it at its own speed (physics/firmware.scheduled_theta), as a drive
        looks its LUT up in its torque task. Made again only when one of those changes (U_dc to 10 mV, and
        only where the LUT has a U_dc axis). Any other mode: no schedule (the setpoints' theta holds)."""
        with self.lock:
            if self.inj_mode != INJ_LUT or self.lut is None:
                return ph.NO_THETA_SCHEDULE
            lut = self.lut
            udc_v = round(self.udc_v, 2) if len(lut.udc_v) > 1 else float(lut.udc_v[0])
            key = (id(lut), self.torque_nm, udc_v, self.gamma_max_rad)
            if self._schedule_key == key:
                return self._schedule
            lo_rpm, hi_rpm = float(lut.speed_rpm[0]), float(lut.speed_rpm[-1])
            n = min(int(math.ceil((hi_rpm - lo_rpm) / SCHEDULE_STEP_RPM)), SCHEDULE_MAX_ROWS - 1) + 1
            step_rpm = (hi_rpm - lo_rpm) / (n - 1) if n > 1 else 0.0
            rows = np.empty((n, 3))
            for i in range(n):
                speed_rpm = lo_rpm + i * step_rpm
                further = self._further_unscaled(speed_rpm)
                rows[i] = (
                    speed_rpm * RPM_TO_RAD_S,
                    *self._clamped(*lut.theta(self.torque_nm, speed_rpm, udc_v), further),
                )
            self._schedule_key, self._schedule = key, rows
            return rows

    def has_pending(self) -> bool:
        """True while setpoint events wait (the plant then runs single chunks)."""
        return bool(self._events)

    def chunk_setpoints(self, sp: np.ndarray, udc_v: float, take_event: bool = True) -> bool:
        """Fill the control loop's setpoints for the next piece. Applies at most one pending event
        and toggles the sync level for it; returns True if it did. take_event False: none (the paced
        plant simulates the samples before the write with the setpoints before it)."""
        with self.lock:
            self.udc_v = udc_v
            applied = False
            if self._events and take_event:
                kind, value = self._events.popleft()
                if kind == "torque":
                    self.torque_nm = float(value)
                elif kind == "theta":
                    self.theta, self.further = value
                elif kind == "inj_mode":
                    self.inj_mode = int(value)
                elif kind == "harmonic_order":
                    self.harmonic_order = int(value)
                elif kind == "decoupling":
                    self.decoupling = int(value)
                elif kind == "voltage_estimate":
                    self.voltage_estimate = int(value)
                self.sync_level ^= 1
                self.events_applied += 1
                applied = True
            sp[ph.S_POWER] = 1.0 if (self.power_on and udc_v >= self.udc_min_v) else 0.0
            sp[ph.S_TORQUE_NM] = self.torque_nm
            sp[ph.S_THETA_COS], sp[ph.S_THETA_SIN] = self.effective_theta()
            further = self.effective_further()
            for k in range(ph.MAX_INJECTION_ORDERS - 1):
                h, c, s = further[k] if k < len(further) else (0, 0.0, 0.0)
                sp[ph.S_XH_ORDER + k], sp[ph.S_XH_COS + k], sp[ph.S_XH_SIN + k] = float(h), c, s
            lut_h = self.inj_mode == INJ_LUT and self.lut is not None
            sp[ph.S_H] = float(self.lut.harmonic_order if lut_h else self.harmonic_order)
            sp[ph.S_DECOUPLING] = float(self.decoupling)
            sp[ph.S_VEST] = float(self.voltage_estimate)
            sp[ph.S_UDC_V] = udc_v
            sp[ph.S_SYNC] = float(self.sync_level)
            return applied

    def publish(
        self, speed_rpm: float, torque_nm: float, udc_v: float, ud_ref_v: float, uq_ref_v: float, current_a: float = 0.0
    ) -> None:
        """Measurements of the control loop, served by SDO (0x606C, 0x6077, 0x6078, 0x6079, 0x2010) and TPDO1."""
        self.speed_rpm = speed_rpm
        self.torque_actual_nm = torque_nm
        self.current_a = current_a
        self.udc_v = udc_v
        self.ud_ref_v = ud_ref_v
        self.uq_ref_v = uq_ref_v

    # -- TPDO1: the actuals ----------------------------------------------------------------------------
    def _current_per_mille(self) -> int:
        return int(np.clip(round(self.current_a / self.rated_current_a * PER_MILLE), -32768, 32767))

    def transmit_actuals(self) -> bool:
        """Send TPDO1 once with the actuals published last (torque, speed, current); only in NMT OPERATIONAL.
        Returns whether it was sent."""
        tpdo = self.node.tpdo[1]
        if not tpdo.enabled or self.node.nmt.state != "OPERATIONAL":
            return False
        values = {
            0x6077: self.read_object(0x6077, 0),
            0x606C: self.read_object(0x606C, 0),
            0x6078: self._current_per_mille(),
        }
        for var in tpdo.map:  # PDO values are not linked to the LocalNode's dictionary: copied here
            var.raw = values[var.index]
        tpdo.transmit()
        return True

    def actuals_loop(self, stop: threading.Event) -> None:
        """The TPDO's event timer (0x1800:5, ms; 0: not sent) in wall time: CAN is a real-time wire even when the
        plant runs faster."""
        while True:
            period_ms = int(self.stored(0x1800, 5))
            if stop.wait(period_ms / 1000.0 if period_ms > 0 else 0.1):
                return
            if period_ms <= 0:
                continue
            try:
                self.transmit_actuals()
            except Exception:  # noqa: BLE001 - one lost frame must not end the drive's actuals
                log.exception("drive: TPDO1 not sent")
