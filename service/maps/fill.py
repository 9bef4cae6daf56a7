"""No holes: a LUT entry for every map cell that stayed non-ok, by one documented rule.

A cell without an entry injects nothing in the drive, and the drive interpolates towards nothing
around it (a LUT with one hole loses its neighbourhood too). A sweep measures its non-ok cells once
more at its end (service/runs/engine.py); a cell that stays non-ok is *filled* here. The fill is flagged in
the map and in every export (VALID stays 1 only for ok cells; FILLED says which cells carry a fill),
and a download chooses whether fills go into the drive.

The rule, per non-ok cell, first that applies:
1. measured: the cell's own theta where its result (or its best attempt in the sweep, where a later one
   ended worse: service/maps/build.py) beat the uncompensated harmonic clearly:
   suppression >= MEASURED_MIN_DB (20 dB: the drive then leaves at most a tenth of the harmonic), or,
   for a `no_authority` cell (gamma_max reached: its theta is the best the injection can do there),
   >= NO_AUTHORITY_MIN_DB (6 dB, half the harmonic).
2. interpolated: from the ok cells around it, along each axis the nearest ok cell on either side on
   the cell's own line (the other coordinates equal), linearly in position between the two, in the
   plane the LUT interpolates in (drivers/lut_image.py: cartesian theta, or polar gamma/delta along the
   shortest arc); the mean over the axes that have both sides (in that plane). An axis with one side
   only holds that side's theta (nearest). Lines with no ok cell give nothing.
3. none: no measured theta good enough and no ok cell on any of its lines: no entry (a download of
   the map needs `force` for it, as for any hole).
Units: theta in rad, suppression in dB, axes in Nm, rpm, V.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Iterable, cast

MEASURED_MIN_DB = 20.0
NO_AUTHORITY_MIN_DB = 6.0
MEASURED_SOURCE = "measured: its own theta"  # rule 1's fill_source begins so (is_measured_fill)
AXES = ("torque_nm", "speed_rpm", "udc_v")
Key = tuple[float, float, float]  # a cell by its AXES values


@dataclass(frozen=True)
class Fill:
    theta_cos: float
    theta_sin: float
    source: str


def _key(cell: dict[str, Any]) -> Key:
    return cast(Key, tuple(float(cell[a]) for a in AXES))  # AXES: three


def _polar(theta: tuple[float, float]) -> tuple[float, float]:
    """(gamma, phase) with phase = atan2(theta_sin, theta_cos) = -delta (the sign does not matter to
    the arc between two of them)."""
    return math.hypot(*theta), math.atan2(theta[1], theta[0])


def _cartesian(gamma: float, phase: float) -> tuple[float, float]:
    return gamma * math.cos(phase), gamma * math.sin(phase)


def blend(points: list[tuple[float, tuple[float, float]]], interpolation: str) -> tuple[float, float]:
    """Weighted mean of thetas [(weight, (cos, sin))] in the LUT's plane: `cartesian` componentwise;
    `polar` gamma linearly and the phase along the shortest arc from the heaviest theta's."""
    total = sum(w for w, _ in points)
    if interpolation == "polar":
        # as the drive does (drivers/lut_image.py): unwrapped against the heaviest theta
        _, reference = _polar(max(points, key=lambda p: p[0])[1])
        gamma = sum(w * _polar(t)[0] for w, t in points) / total
        phase = reference + sum(w * math.remainder(_polar(t)[1] - reference, 2 * math.pi) for w, t in points) / total
        return _cartesian(gamma, phase)
    return (sum(w * t[0] for w, t in points) / total, sum(w * t[1] for w, t in points) / total)


def fill_cells(
    cells: Iterable[dict[str, Any]], axes: dict[str, list[float]], interpolation: str = "cartesian"
) -> dict[Key, Fill]:
    """{(torque, speed, udc): Fill} for the non-ok cells the rule fills (module doc). cells: dicts with
    the axes' keys, status, theta_cos, theta_sin and suppression_db (the cell's current result)."""
    cells = list(cells)
    ok = {
        _key(c): (float(c["theta_cos"]), float(c["theta_sin"]))
        for c in cells
        if c.get("status") == "ok" and c.get("theta_cos") is not None
    }
    fills: dict[tuple[float, float, float], Fill] = {}
    for c in cells:
        status = c.get("status") or "missing"
        if status == "ok":
            continue
        key = _key(c)
        measured = _measured(c, status)
        if measured is not None:
            fills[key] = measured
            continue
        interpolated = _interpolated(key, ok, axes, interpolation)
        if interpolated is not None:
            fills[key] = interpolated
    return fills


def _measured(c: dict[str, Any], status: str) -> Fill | None:
    db = c.get("suppression_db")
    if c.get("theta_cos") is None or db is None:
        return None
    floor = NO_AUTHORITY_MIN_DB if status == "no_authority" else MEASURED_MIN_DB
    if db < floor:
        return None
    attempt = f", from its attempt result {c['attempt_id']}" if c.get("attempt_id") is not None else ""
    return Fill(
        float(c["theta_cos"]),
        float(c["theta_sin"]),
        f"{MEASURED_SOURCE} ({status}, {db:.1f} dB against the uncompensated harmonic{attempt})",
    )


def is_measured_fill(fill_source: str | None) -> bool:
    """Whether a filled cell's entry is its own measured theta (rule 1), not one made from its neighbours."""
    return fill_source is not None and fill_source.startswith(MEASURED_SOURCE)


def _interpolated(
    key: tuple[float, float, float],
    ok: dict[Key, tuple[float, float]],
    axes: dict[str, list[float]],
    interpolation: str,
) -> Fill | None:
    between = interpolate_between(key, ok, axes, interpolation)
    if between is not None:
        return between
    return _held(key, ok, axes)


def interpolate_between(
    key: tuple[float, float, float],
    ok: dict[Key, tuple[float, float]],
    axes: dict[str, list[float]],
    interpolation: str,
) -> Fill | None:
    """theta at `key` from the ok cells on either side of it along each axis of its lines (rule 2;
    ok: {(torque, speed, udc): (theta_cos, theta_sin)}); None where no axis has both sides."""
    per_axis: list[tuple[float, float]] = []
    sides: list[str] = []
    for i, axis in enumerate(AXES):
        values = sorted(float(v) for v in axes[axis])
        x = key[i]
        below = [v for v in values if v < x and _with(key, i, v) in ok]
        above = [v for v in values if v > x and _with(key, i, v) in ok]
        if below and above:
            lo, hi = max(below), min(above)
            f = (x - lo) / (hi - lo)
            per_axis.append(blend([(1.0 - f, ok[_with(key, i, lo)]), (f, ok[_with(key, i, hi)])], interpolation))
            sides.append(f"{axis} between {lo:g} and {hi:g}")
    if not per_axis:
        return None
    theta = blend([(1.0, t) for t in per_axis], interpolation)
    return Fill(theta[0], theta[1], f"interpolated ({interpolation}) from ok cells: " + "; ".join(sides))


def _held(
    key: tuple[float, float, float], ok: dict[Key, tuple[float, float]], axes: dict[str, list[float]]
) -> Fill | None:
    """No axis with ok cells on both sides: hold the nearest ok cell on the cell's lines."""
    nearest = None
    for i, axis in enumerate(AXES):
        for v in axes[axis]:
            other = _with(key, i, float(v))
            if other != key and other in ok:
                span = max(float(max(axes[axis])) - float(min(axes[axis])), 1e-12)
                distance = abs(float(v) - key[i]) / span
                if nearest is None or distance < nearest[0]:
                    nearest = (distance, other, axis)
    if nearest is None:
        return None
    _, other, axis = nearest
    theta = ok[other]
    return Fill(
        theta[0],
        theta[1],
        f"held from the nearest ok cell along {axis} ({other[0]:g} Nm, {other[1]:g} rpm, {other[2]:g} V)",
    )


def _with(key: tuple[float, float, float], i: int, value: float) -> tuple[float, float, float]:
    out = list(key)
    out[i] = value
    return cast(Key, tuple(out))
