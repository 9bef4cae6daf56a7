"""A map's LUT judged along run-ups (issue 27): where the motor runs, between the grid's speeds.

At every torque of the map's finer torque axis (each row and the midpoint between neighbouring rows) and each
U_dc, two run-ups over the map's speed range (service/runs/runup.py): injection off (the uncompensated order)
and the drive's LUT in force (the residual), tracking the map's harmonic order among every order of the run-up's
survey (fitted together, so none leaks into it). Every speed bin of the pair is one judged point of kind `runup`:
  - suppression_db = 20 log10(|A_off| / |A_lut|) of the bin (as a grid point's figure);
  - above_floor_db = 20 log10(|A_off| / floor), floor the bin's noise floor of the uncompensated run-up
    (service/model/order_tracking.py: the rms amplitude an order without a tone shows there);
  - it holds when suppression_db >= target_db, or when the residual lies target_db below the median
    uncompensated level of the run-up's range (where the order itself nearly vanishes, as at a resonance's
    anti-node, a relative figure means nothing: the floor rule judges it against the range);
  - harm (`is_harm`): a point whose residual is above its uncompensated level by more than the measurement's
    repeatability (suppression < -HARM_MARGIN_DB) where the order stands >= HARM_ABOVE_FLOOR_DB over the noise
    floor is the LUT making the ripple worse, said in its reason.
The speed range of a torque is the map's speed range narrowed to where the envelope model of the motor
settings holds the torque (a torque row past its field-weakening limit is run up to that limit only); a
torque with no such range is not run up.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from service.bench.run import BenchRun
from service.model.limits import outside_envelope
from service.model.operating_point import OperatingPoint
from service.runs.runup import RunupRequest, measure_runup
from service.settings import Settings

HARM_ABOVE_FLOOR_DB = 20.0  # an order this far above its noise floor made worse by the LUT: harm
# ... by more than this: what two run-ups with the same injection differ by in a bin (measured where the drive injects
# nothing, LUT intervals with injection off, paper-bench: within 0.2 dB at >= 20 dB above the floor)
HARM_MARGIN_DB = 0.5
RANGE_STEP_RPM = 10.0  # the envelope is checked along the range at this step


def runup_torques(torque_axis: list[float], most: int | None = None) -> list[tuple[float, str]]:
    """Each torque row and the midpoint between neighbouring rows: (torque_nm, row | midpoint); with `most`, at
    most that many of them, evenly spread by index with both ends kept."""
    values = sorted(float(t) for t in torque_axis)
    out: list[tuple[float, str]] = []
    for a, b in zip(values, values[1:]):
        out += [(a, "row"), ((a + b) / 2.0, "midpoint")]
    out.append((values[-1], "row"))
    if most is None or len(out) <= most:
        return out
    picked = sorted({round(k * (len(out) - 1) / (most - 1)) for k in range(most)})
    return [out[i] for i in picked]


def runup_range(
    torque_nm: float, udc_v: float, speeds_rpm: list[float], settings: Settings, override_envelope_model: bool
) -> tuple[float, float] | None:
    """The map's speed range from its lowest speed up to where the envelope model stops holding `torque_nm`
    (None: not even a bin's width of it holds)."""
    lo, hi = min(speeds_rpm), max(speeds_rpm)
    last_inside: float | None = None
    for speed in np.arange(lo, hi + RANGE_STEP_RPM / 2, RANGE_STEP_RPM):
        op = OperatingPoint(torque_nm=torque_nm, speed_rpm=float(min(speed, hi)), udc_v=udc_v)
        if outside_envelope(op, settings, override_envelope_model) is not None:
            break
        last_inside = float(min(speed, hi))
    if last_inside is None or last_inside - lo < RANGE_STEP_RPM:
        return None
    return lo, last_inside


def is_harm(suppression_db: float | None, above_floor_db: float | None, no_injection: bool = False) -> bool:
    """The LUT made the order worse than no compensation, beyond what a measurement repeats to (module doc); never
    where the drive injects nothing (`no_injection`, mark_no_injection)."""
    return (
        not no_injection
        and suppression_db is not None
        and above_floor_db is not None
        and suppression_db < -HARM_MARGIN_DB
        and above_floor_db >= HARM_ABOVE_FLOOR_DB
    )


def mark_no_injection(cells: list[dict[str, Any]], nothing: Callable[[Mapping[str, Any], float], bool]) -> None:
    """Mark each measured point where the drive's LUT injects exactly nothing (`nothing(point, half_width_rpm)`,
    service/maps/lut_export.py injects_nothing: a cell turned off, LUT flag 3, is a corner of its interval, or of
    every interval its run-up bin spans) `no_injection`: its figure is no compensation by construction, two
    measurements without injection compared, so never harm (is_harm) however far the two differ."""
    for c in cells:
        if c.get("status") != "measured" or c.get("suppression_db") is None:
            continue
        if nothing(c["operating_point"], (c.get("bin_rpm") or 0.0) / 2.0):
            c["no_injection"] = True
            if not c.get("holds"):
                c["reason"] = (
                    f"the drive injects nothing here (injection off in the LUT): {c['suppression_db']:.1f} dB is what "
                    "two measurements without injection differ by"
                )


def _db(ratio: float) -> float:
    return 20.0 * math.log10(ratio)


def judge_bins(
    off: dict[str, Any], lut: dict[str, Any], order: int, torque_nm: float, udc_v: float, target_db: float
) -> list[dict[str, Any]]:
    """Every speed bin both run-ups have, as a judged point (module doc)."""
    k_off, k_lut = off["orders"].index(order), lut["orders"].index(order)
    lut_by_speed = dict(zip(lut["speed_rpm"], lut["amplitude"][k_lut]))
    levels = [a for a in off["amplitude"][k_off] if a is not None and a > 0]
    if not levels:
        return []
    reference_fs = statistics.median(levels)  # the range's median uncompensated level
    floor_rule_fs = reference_fs * 10.0 ** (-target_db / 20.0)
    cells = []
    for speed, a_off, floor in zip(off["speed_rpm"], off["amplitude"][k_off], off["noise_floor"]):
        a_lut = lut_by_speed.get(speed)
        if a_off is None or a_lut is None or not (a_off > 0 and a_lut > 0) or floor is None or floor <= 0:
            continue  # a bin one of the two did not fit: no figure
        suppression_db = _db(a_off / a_lut)
        above_floor_db = _db(a_off / floor)
        holds = suppression_db >= target_db or a_lut <= floor_rule_fs
        if holds:
            reason = None if suppression_db >= target_db else "below the floor rule (the order nearly vanishes here)"
        elif is_harm(suppression_db, above_floor_db):
            reason = (
                f"the LUT makes the order worse here ({suppression_db:.1f} dB), {above_floor_db:.0f} dB above the floor"
            )
        else:
            reason = f"{suppression_db:.1f} dB, below the target of {target_db:g} dB"
        cells.append(
            {
                "operating_point": {"torque_nm": torque_nm, "speed_rpm": float(speed), "udc_v": udc_v},
                "kind": "runup",
                "status": "measured",
                "error": None,
                "suppression_db": suppression_db,
                "above_floor_db": above_floor_db,
                "holds": holds,
                "reason": reason,
                "uncompensated_fs": a_off,
                "residual_fs": a_lut,
                "floor_rule_fs": floor_rule_fs,
                "bin_rpm": off.get("bin_rpm"),  # the bin spans speed_rpm +- bin_rpm / 2 (mark_no_injection)
            }
        )
    return cells


def measure_runup_pair(
    brun: BenchRun,
    settings: Settings,
    torque_nm: float,
    udc_v: float,
    speed_range: tuple[float, float],
    rate_rpm_per_s: float,
    target_db: float,
    uncompensated: dict[tuple[float, ...], dict[str, Any]] | None = None,
) -> tuple[list[dict[str, Any]], float, bool]:
    """The pair of run-ups at one torque in the open run (off, then the LUT): its judged bins, the plant seconds
    it took and whether the uncompensated run-up was reused. `uncompensated`: the uncompensated run-ups a caller
    keeps for the same bench and ramp (a refinement's rounds validate maps of one bench over one range: the order
    without injection does not change with the LUT), taken from it and added to it."""
    order = brun.harmonic_order
    results = {}
    key = (torque_nm, udc_v, *speed_range, rate_rpm_per_s, float(order))
    reused = uncompensated is not None and key in uncompensated
    if uncompensated is not None and reused:
        results["off"] = {**uncompensated[key], "plant_time_s": 0.0}  # paid for once, where it was measured
    for injection in ("off", "lut"):
        if injection in results:
            continue
        req = RunupRequest(
            torque_nm=torque_nm,
            udc_v=udc_v,
            speed_rpm=speed_range,
            rate_rpm_per_s=rate_rpm_per_s,
            injection=injection,
            # every order of the survey fitted, not only the map's: an unfitted order leaks into it (order_tracking),
            # and the injection's own 2h, amplified where it crosses the sensor's resonance, read as a failing bin
            orders=None,
            override_envelope_model=True,  # the range was narrowed to the envelope already (runup_range)
        )
        results[injection] = measure_runup(brun, settings, req)
    if uncompensated is not None and not reused:
        uncompensated[key] = results["off"]
    plant_s = sum(r["plant_time_s"] for r in results.values())
    return judge_bins(results["off"], results["lut"], order, torque_nm, udc_v, target_db), plant_s, reused
