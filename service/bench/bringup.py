"""The bring-up check (issue 29): what is wired wrong, found before the first point, one line per check with what
was found and the fix (`ripplecal bench check`, GET /api/v1/bench/check; DESIGN section 6).

Without a spin it only reads: the links as the bench opened them (bus, each node at its id with the identity and
device type of the EDS we hold, the supply, the DAQ at its configured rate: BenchLinks.open names the first that
fails and its fix), each node's heartbeat producer (0x1017) and its consumer of ours (0x1016), the DAQ line since
it opened (CRC failures, sequence gaps, data age) and the supply (*IDN?, its measured voltage against its set one).
With a spin (`spin`: the bench turned at SPIN_RPM without torque, as any run: interlocks armed, made safe at the
end) it also checks what only a turning shaft shows: the electrical angle advancing with the sign and the rate
that the drive's velocity actual (0x606C) and motor.pole_pairs predict, the accelerometer neither silent nor over
range, and the sync line toggling on the setpoints the move writes.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from drivers.drive import ACTUALS_OBJECTS, ACTUALS_TPDO
from service.bench.bench import Bench
from service.bench.point_stream import PointStream
from service.identification.session import MeasurementError
from service.model.operating_point import OperatingPoint
from service.settings import Settings

SPIN_RPM = 300.0  # slow: a mis-wired angle or sensor is found before any torque is asked for
SPIN_TORQUE_NM = 0.0
SPIN_SAMPLES_S = 0.25  # plant seconds of DAQ samples judged at the spin
RATE_TOLERANCE = 0.05  # the angle's rate within 5 % of velocity actual x pole pairs
ACCEL_SILENT_FS = 1e-5  # rms below this: no sensor on the input (the ADC's own noise is above it)
ACCEL_OVER_FS = 0.95  # |accel| above this share of full scale: over range
SUPPLY_TOLERANCE_V = 0.5  # the supply's measured voltage within this of its set one (or 5 %)


@dataclass(frozen=True)
class Check:
    """One line of the check: what it looked at, whether it passed, what it found, and the fix when it did not."""

    name: str
    ok: bool
    detail: str
    fix: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def check_bench(bench: Bench, settings: Settings, spin: bool = False) -> list[Check]:
    """Every check in order (module doc); never raises for what it finds."""
    if not bench.connected:
        return [_unreachable(bench)]
    lines = [Check("links", True, _links_text(settings))]
    lines += _nodes(bench, settings)
    lines.append(_actuals_pdo(bench))
    lines.append(_daq_line(bench))
    lines.append(_supply(bench))
    lines += (
        _spin(bench, settings)
        if spin
        else [Check("spin", True, "not run: the angle, accelerometer and sync-line checks need --spin (spin=true)")]
    )
    return lines


def _unreachable(bench: Bench) -> Check:
    u = bench.unreachable or {}
    if not u:
        return Check(
            "links", False, "the bench is not connected", "start the service with the bench file of this bench"
        )
    return Check(
        f"links: {u.get('device')}",
        False,
        f"{u.get('device')} at {u.get('address')}: {u.get('error')} ({u.get('left')})",
        u.get("hint"),
    )


def _links_text(settings: Settings) -> str:
    s = settings
    return (
        f"CAN {s.can.interface} {s.can.channel}, drive node {s.can.drive_node} and load node {s.can.load_node} "
        f"answering with their EDS identity, supply {s.supply.url}, DAQ {s.daq.url} at its configured "
        f"{s.daq.sample_rate_hz:g} frames/s"
    )


def _nodes(bench: Bench, settings: Settings) -> list[Check]:
    lines = []
    service_node = settings.can.service_node_id
    for kind, master, key in (("drive", bench.drive, "drive_node"), ("load", bench.load, "load_node")):
        if master is None:
            continue
        name = f"{kind} node {master.node_id}"
        try:
            lines.append(Check(f"{name}: identity", True, master.check_identity()))
        except Exception as exc:  # noqa: BLE001 - what the node answered is the finding
            lines.append(
                Check(
                    f"{name}: identity",
                    False,
                    f"{type(exc).__name__}: {exc}",
                    f"can.{key} is the {kind}'s node id (are can.drive_node and can.load_node swapped?)",
                )
            )
            continue
        producer = master.heartbeat_period_ms
        try:
            consumer = master.heartbeat_consumer()
        except Exception as exc:  # noqa: BLE001
            lines.append(Check(f"{name}: heartbeats", False, f"0x1016:1 not readable: {exc}", "check the node's EDS"))
            continue
        consumer_node, consumer_ms = consumer >> 16, consumer & 0xFFFF
        problems = []
        if not producer:
            problems.append("it produces no heartbeat (0x1017 = 0)")
        if consumer_node != service_node or consumer_ms == 0:
            problems.append(f"it does not consume the service's heartbeat (0x1016:1 = 0x{consumer:08X})")
        elif consumer_ms <= settings.can.heartbeat_period_ms:
            problems.append(
                f"its consumer time {consumer_ms} ms is not above our period {settings.can.heartbeat_period_ms} ms"
            )
        detail = (
            f"produces every {producer} ms (0x1017); consumes node {consumer_node}'s within {consumer_ms} ms (0x1016:1)"
        )
        lines.append(
            Check(
                f"{name}: heartbeats",
                not problems,
                detail if not problems else "; ".join(problems),
                None if not problems else "set 0x1017 to a period and let the service arm 0x1016 (restart it)",
            )
        )
    return lines


def _actuals_pdo(bench: Bench) -> Check:
    """The drive's TPDO of the actuals mapped as the service expects: the device's mapping (0x1A00 + n - 1, read by
    SDO) against the EDS the service reads it with, and the torque, velocity and current actual in it."""
    drive = bench.drive
    if drive is None:
        return Check("drive TPDO mapping", False, "no drive", "can.drive_node names the drive")
    index = 0x1A00 + ACTUALS_TPDO - 1
    try:
        device, expected = drive.actuals_mapping()
    except Exception as exc:  # noqa: BLE001 - what it answered is the finding
        return Check("drive TPDO mapping", False, f"0x{index:04X} not readable: {exc}", "check the drive's EDS")
    text = ", ".join(f"0x{m >> 16:04X}" for m in device)
    objects = {m >> 16 for m in device}
    if device != expected or not set(ACTUALS_OBJECTS) <= objects:
        return Check(
            "drive TPDO mapping",
            False,
            f"TPDO{ACTUALS_TPDO} maps {text or 'nothing'}; the EDS the service reads it with maps "
            + ", ".join(f"0x{m >> 16:04X}" for m in expected),
            f"map the drive's TPDO{ACTUALS_TPDO} as its EDS (0x{index:04X}: torque 0x6077, velocity 0x606C, current "
            "0x6078), or give the service the drive's own EDS",
        )
    return Check("drive TPDO mapping", True, f"TPDO{ACTUALS_TPDO} maps {text}, as the EDS")


def _daq_line(bench: Bench) -> Check:
    daq = bench.daq
    if daq is None:
        return Check("DAQ line", False, "no DAQ reader", "daq.url names the DAQ's port")
    h = daq.health()
    # the first resync is the reader finding the stream when it opened: only more are the line's
    bad = {k: h[k] for k in ("crc_failures", "sequence_gaps") if h.get(k)}
    if h.get("resyncs", 0) > 1:
        bad["resyncs"] = h["resyncs"]
    detail = (
        f"{h['frames']} frames since it opened, CRC failures {h['crc_failures']}, sequence gaps {h['sequence_gaps']}, "
        f"resyncs {h['resyncs']}; data age {h['data_age_s']} s"
    )
    if not h["connected"]:
        return Check("DAQ line", False, f"not connected: {h['last_error']}", "plug the DAQ in; daq.url names its port")
    return Check(
        "DAQ line",
        not bad,
        detail,
        None if not bad else "a clean cable and the DAQ's baud rate / USB port: the line loses or damages frames",
    )


def _supply(bench: Bench) -> Check:
    supply = bench.supply
    if supply is None:
        return Check("DC supply", False, "no supply", "supply.url names the supply's port")
    try:
        identity = supply.identify()
        output_on = supply.query("OUTP?").strip() in ("1", "ON")
        set_v, measured_v = supply.voltage_setpoint(), supply.measure_voltage()
    except Exception as exc:  # noqa: BLE001 - what it answered is the finding
        return Check(
            "DC supply", False, f"{type(exc).__name__}: {exc}", "supply.url names an SCPI supply that answers *IDN?"
        )
    if not output_on:
        return Check(
            "DC supply",
            True,
            f"*IDN? {identity!r}; output off while idle (a run switches it on; --spin checks that it follows its set "
            f"{set_v:.2f} V)",
        )
    return _follows("DC supply", identity, set_v, measured_v)


def _follows(name: str, identity: str, set_v: float, measured_v: float) -> Check:
    """The supply's measured voltage against its set one, its output on."""
    tolerance = max(SUPPLY_TOLERANCE_V, 0.05 * abs(set_v))
    follows = abs(measured_v - set_v) <= tolerance
    detail = f"*IDN? {identity!r}; set {set_v:.2f} V, measured {measured_v:.2f} V"
    return Check(
        name,
        follows,
        detail if follows else detail + f": {abs(measured_v - set_v):.2f} V apart (more than {tolerance:.2f} V)",
        None if follows else "the supply's output is on and its sense leads are at the DC link",
    )


def _spin(bench: Bench, settings: Settings) -> list[Check]:
    """The shaft turned slowly without torque: the angle against velocity actual and pole pairs, the accelerometer,
    and the sync line (the move's setpoints are confirmed by it)."""
    op = OperatingPoint(torque_nm=SPIN_TORQUE_NM, speed_rpm=SPIN_RPM, udc_v=_spin_udc(settings))
    pole_pairs = settings.motor.pole_pairs
    sync_fix = "wire the drive's sync output to the DAQ's sync input, or set daq.sync_input = false"
    n = max(256, int(SPIN_SAMPLES_S * settings.daq.sample_rate_hz))
    settle_error: str | None = None
    follows: Check | None = None
    try:
        with bench.run(settings.identification.harmonic_order) as run:
            try:
                with run.operating_point(op) as session:
                    samples = session.stream.next(n)
                    follows = _supply_at_spin(bench)
            except MeasurementError as exc:
                # the move did not settle (a reversed angle or wrong pole pairs read as the wrong speed): the load
                # still turns the shaft, so its raw samples still tell why
                settle_error = f"{type(exc).__name__}: {exc}"
                samples = PointStream(bench.accounting, settings.daq.sample_rate_hz, guard=run.guard).next(n)
            velocity_rpm = float(bench.drive.read(0x606C)) if bench.drive is not None else float("nan")
    except Exception as exc:  # noqa: BLE001 - a spin that could not run: its reason is the finding
        text = f"{type(exc).__name__}: {exc}"
        sync = "sync" in text.lower() or "setpoint" in text.lower()
        return [
            Check(
                "spin",
                False,
                f"the spin at {SPIN_RPM:g} rpm without torque did not run: {text}",
                sync_fix
                if sync and settings.daq.sync_input
                else "the load machine turns the shaft and the DAQ angle is the shaft's",
            )
        ]
    lines = (
        [Check("sync line", True, "it toggled on every setpoint of the move (each confirmed)")]
        if settings.daq.sync_input and settle_error is None
        else []
    )
    if follows is not None:
        lines.append(follows)
    angle = np.unwrap(samples.angle_rad)
    seconds = (samples.index[-1] - samples.index[0]) / settings.daq.sample_rate_hz
    measured_rad_s = float(angle[-1] - angle[0]) / seconds if seconds > 0 else float("nan")
    expected_rad_s = velocity_rpm * 2.0 * math.pi / 60.0 * pole_pairs
    lines.append(_angle(measured_rad_s, expected_rad_s, velocity_rpm, pole_pairs))
    lines.append(_accelerometer(samples.accel_fs))
    if settle_error is not None:
        explained = any(not line.ok for line in lines)
        sync = settings.daq.sync_input and ("sync" in settle_error.lower() or "setpoint" in settle_error.lower())
        lines.append(
            Check(
                "spin",
                False,
                f"the move to {SPIN_RPM:g} rpm did not settle: {settle_error}"
                + (" (the checks above say why)" if explained else ""),
                sync_fix
                if sync
                else (
                    "fix what the checks above name"
                    if explained
                    else "the load machine turns the shaft at its setpoint"
                ),
            )
        )
    return lines


def _supply_at_spin(bench: Bench) -> Check | None:
    """The supply with its output on for the run: does it follow its set voltage."""
    supply = bench.supply
    if supply is None:
        return None
    return _follows("DC supply at the spin", supply.identify(), supply.voltage_setpoint(), supply.measure_voltage())


def _spin_udc(settings: Settings) -> float:
    """The DC link the spin runs at: the settings' nominal, inside the bench's limits."""
    s = settings.safety
    return float(min(max(12.0, s.min_udc_v), s.max_udc_v))


def _angle(measured_rad_s: float, expected_rad_s: float, velocity_rpm: float, pole_pairs: int) -> Check:
    detail = (
        f"electrical angle advances at {measured_rad_s:.1f} rad/s; velocity actual {velocity_rpm:.1f} rpm x "
        f"{pole_pairs} pole pairs predicts {expected_rad_s:.1f} rad/s"
    )
    if not (math.isfinite(measured_rad_s) and math.isfinite(expected_rad_s)) or expected_rad_s == 0.0:
        return Check("angle", False, detail, "the load machine turns the shaft (velocity actual reads 0)")
    ratio = measured_rad_s / expected_rad_s
    if ratio < 0:
        return Check(
            "angle",
            False,
            detail + ": it runs backwards",
            "swap the encoder's A and B (or its direction setting): the DAQ's angle must rise with positive speed",
        )
    if abs(ratio - 1.0) > RATE_TOLERANCE:
        pairs = ratio * pole_pairs
        return Check(
            "angle",
            False,
            detail + f": {ratio:.2f} x the prediction",
            f"motor.pole_pairs is {pole_pairs}, the angle says {pairs:.2f}: set motor.pole_pairs = {round(pairs)}"
            if abs(pairs - round(pairs)) < 0.1 and round(pairs) >= 1
            else "the DAQ's angle is the electrical angle of this motor (counts per turn and pole pairs)",
        )
    return Check("angle", True, detail)


def _accelerometer(accel_fs: np.ndarray) -> Check:
    rms = float(np.sqrt(np.mean(np.square(accel_fs)))) if len(accel_fs) else 0.0
    peak = float(np.max(np.abs(accel_fs))) if len(accel_fs) else 0.0
    detail = f"rms {rms:.2e} of full scale, peak {peak:.3f} at {SPIN_RPM:g} rpm"
    if rms < ACCEL_SILENT_FS:
        return Check(
            "accelerometer",
            False,
            detail + ": silent",
            "the accelerometer is connected and powered (its cable at the DAQ)",
        )
    if peak > ACCEL_OVER_FS:
        return Check(
            "accelerometer",
            False,
            detail + ": over range",
            "a larger range (daq.accel_full_scale_rad_s2 and the sensor's) or a less sensitive mounting",
        )
    return Check("accelerometer", True, detail)
