"""Map quality: each cell's theta against its grid neighbours', outliers flagged with a reason.

Arithmetic in theta = (theta_cos, theta_sin), rad (docs/conventions.md, Injection and theta: never gamma/delta,
which wrap at 0/360 deg).
Only `ok` cells take part (a filled cell, service/maps/fill.py, carries a fill, not a measurement: it is
neither judged nor a reference, but for a below-target cell's fill of its own measured theta: a reference); a
cell's neighbours are the cells one grid index away along each axis. Axes may be non-uniform (a refined map inserts breakpoints): every step is scaled by the real
spacing, and the fit interpolates by position.

The statistic (robust, scaled by the grid spacing):
- typical gradient per axis k: g_k = median over adjacent reference pairs along k of
  |theta_a - theta_b| / |x_a - x_b| (rad per Nm, per rpm, per V), each pair weighted by |x_a - x_b| (the
  median change per unit of the axis: a refined map's close breakpoints at a turn do not make the turn
  the whole map's typical change); a median of absolute differences, so up to half the axis may be
  spoiled without moving it;
- a cell's fit: the component-wise median of its reference neighbours' theta, each pair across the
  cell on one axis (at distances d_lo, d_hi) centred on its interpolation at the cell's position
  I = w_lo theta_lo + w_hi theta_hi, w_lo = d_hi / (d_lo + d_hi), w_hi = d_lo / (d_lo + d_hi): both
  shifted by I - (theta_lo + theta_hi) / 2 = (w_lo - 1/2) (theta_lo - theta_hi) (0 on a uniform axis;
  on a non-uniform one the plain median would lean towards the farther neighbour). Each neighbour
  stays one value of the median, and a bad one moves its partner's by |w_lo - 1/2| of its error at
  most (none on a uniform axis), so one bad neighbour is still outvoted. Exact for an interior
  cell of a map linear in the operating point, on any spacing (each pair is then symmetric about it).
  A lone neighbour on an axis (an axis end, or the other side not a reference) is extrapolated along the
  line through it and the next reference beyond it (when that one is at least as far from it as the cell:
  never stretched over more than its own span), and their change per unit is that axis's local change
  below: a low-torque edge row, where theta* changes fast with torque at the turn, is not an outlier of
  its one neighbour row;
- its expected step: the median over those neighbours of max(g_k, l_k) |x_neighbour - x_cell|, l_k the
  change across the cell, |theta_hi - theta_lo| / (x_hi - x_lo) of its pair on axis k (where theta* turns
  fast, as at the field-weakening turn that a refinement resolves with close breakpoints, the turn its two
  neighbours agree on is not an outlier; a single bad cell leaves l_k of its own pair small), floored at
  MIN_STEP_DEG (a flat map's noise is not an outlier);
- score = |theta - fit| / expected step; an outlier when score > OUTLIER_FACTOR.
References are the ok cells not yet flagged: the worst cell over the factor is flagged, then every
statistic is computed again without it, until none is left (one outlier cannot make its neighbours
look wrong); after a quarter of the ok cells, the rest over the factor are flagged at once (a map
that noisy has no few bad points to single out, and a read stays fast). A cell with fewer than MIN_NEIGHBOURS reference neighbours is `unchecked`: with one
neighbour there is no telling which of the two is off.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Container
from dataclasses import dataclass, field
from typing import Any

from service.maps.fill import is_measured_fill
from service.model.secondary_path import gamma_delta

AXES = ("torque_nm", "speed_rpm", "udc_v")
AXIS_UNITS = {"torque_nm": "Nm", "speed_rpm": "rpm", "udc_v": "V"}
OUTLIER_FACTOR = 3.0
MIN_NEIGHBOURS = 2
ONE_BY_ONE_SHARE = 0.25  # of the ok cells flagged one by one; the rest over the factor at once
MIN_STEP_DEG = 0.05  # ~1.7 % of a 3 deg gamma: below that a deviation costs < 1 dB at 40 dB
QUALITIES = ("consistent", "outlier", "unchecked", "smoothed")
# the map cell's quality fields (MapCellPublic): the JSON export's `cells` leave them out, so its
# format_version 1 stays as it was; the export carries them in its top-level `quality` instead
CELL_FIELDS = ("quality", "outlier_reason", "smoothed_from")

Key = tuple[float, float, float]


@dataclass
class CellQuality:
    quality: str  # consistent | outlier | unchecked
    fit: tuple[float, float] | None = None  # neighbours' median theta (cos, sin), rad
    neighbours: list[Key] = field(default_factory=list)
    deviation_rad: float | None = None
    expected_step_rad: float | None = None
    reason: str | None = None

    @property
    def score(self) -> float | None:
        if self.deviation_rad is None or not self.expected_step_rad:
            return None
        return self.deviation_rad / self.expected_step_rad


@dataclass
class MapQuality:
    cells: dict[Key, CellQuality]  # ok cells only (a fill of a cell's own theta is a reference, not judged)
    gradient_rad_per_unit: dict[str, float | None]  # g_k per axis (of the final references)

    def count(self, quality: str) -> int:
        return sum(1 for c in self.cells.values() if c.quality == quality)


def cell_key(cell: dict[str, Any]) -> Key:
    return (float(cell["torque_nm"]), float(cell["speed_rpm"]), float(cell["udc_v"]))


def assess(cells: list[dict[str, Any]], axes: dict[str, list[float]]) -> MapQuality:
    """Quality of every ok cell of a map (cells as MapCellPublic dicts, axes as the map's)."""
    # filled cells are not ok (their theta is a fill, not a measurement): skipped with the other non-ok, but for a
    # below-target cell's fill of its own theta (>= fill.MEASURED_MIN_DB; not no_authority's, clamped at gamma_max):
    # theta* measured, a reference for its neighbours, never judged (at the turn, where |theta*| passes near zero,
    # such cells are common: without them a turn cell has a neighbour on one side only, and its loop reads as an outlier)
    theta = {
        cell_key(c): (float(c["theta_cos"]), float(c["theta_sin"]))
        for c in cells
        if (c["status"] == "ok" and not c.get("filled"))
        or (c["status"] == "below_target" and c.get("filled") and is_measured_fill(c.get("fill_source")))
        if c.get("theta_cos") is not None and c.get("theta_sin") is not None
    }
    judged = [cell_key(c) for c in cells if c["status"] == "ok" and not c.get("filled") and cell_key(c) in theta]
    values = {a: sorted({float(x) for x in axes.get(a) or []}) for a in AXES}
    index = {a: {v: i for i, v in enumerate(values[a])} for a in AXES}
    # each ok cell's ok neighbours: (neighbour, axis, spacing), found once
    near: dict[Key, list[tuple[Key, str, float]]] = {}
    for key in theta:
        near[key] = []
        for pos, a in enumerate(AXES):
            i = index[a].get(key[pos])
            for j in () if i is None else (i - 1, i + 1):
                if 0 <= j < len(values[a]):
                    other = key[:pos] + (values[a][j],) + key[pos + 1 :]
                    if other in theta:
                        near[key].append((other, a, abs(values[a][j] - key[pos])))
    # |delta theta| / spacing of every adjacent pair, per axis, computed once
    pairs = [
        (k, other, a, math.hypot(theta[other][0] - theta[k][0], theta[other][1] - theta[k][1]) / dx, dx)
        for k, around in near.items()
        for other, a, dx in around
        if other > k
    ]
    flagged: set[Key] = set()
    why: dict[Key, CellQuality] = {}  # each outlier as it was when flagged (its fit may lose references later)
    axis_values = [values[a] for a in AXES]
    fits = {k: _fit(k, near[k], theta, axis_values, flagged) for k in judged}
    # more outliers than a quarter of the cells: a noisy map, not a few bad points; the cells then
    # over the factor are all flagged at once instead of one by one
    one_by_one = max(1, int(len(judged) * ONE_BY_ONE_SHARE))
    while True:
        gradients = _gradients(pairs, flagged)
        evaluated = {k: _evaluate(fits[k], gradients) for k in judged}
        over = sorted(
            (
                (c.score, k)
                for k, c in evaluated.items()
                if k not in flagged and c.score is not None and c.score > OUTLIER_FACTOR
            ),
            reverse=True,
        )
        if not over:
            break
        if len(flagged) >= one_by_one:
            flagged.update(k for _, k in over)
            why.update((k, evaluated[k]) for _, k in over)
            break
        worst = over[0][1]
        flagged.add(worst)
        why[worst] = evaluated[worst]
        for other, _, _ in near[worst]:  # only the worst's neighbours lose a reference
            if other in fits:
                fits[other] = _fit(other, [n for n in near[other] if n[0] not in flagged], theta, axis_values, flagged)
    if len(flagged) > one_by_one:  # flagged at once: the fits without all of them
        fits = {k: _fit(k, [n for n in near[k] if n[0] not in flagged], theta, axis_values, flagged) for k in judged}
        evaluated = {k: _evaluate(fits[k], gradients) for k in judged}
    for k in flagged:
        evaluated[k] = why[k]
        evaluated[k].quality = "outlier"
        evaluated[k].reason = _reason(theta[k], evaluated[k], gradients)
    return MapQuality(evaluated, gradients)


def _gradients(pairs: list[tuple[Key, Key, str, float, float]], flagged: set[Key]) -> dict[str, float | None]:
    """Per axis, the median of the pairs' |delta theta| / spacing, each pair weighted by its spacing: the median
    change per unit along the axis (a refined map's close breakpoints at a turn are many pairs over a few rpm,
    and would otherwise make the whole map's typical change the turn's)."""
    per_axis: dict[str, list[tuple[float, float]]] = {a: [] for a in AXES}
    for k, other, a, g, dx in pairs:
        if k not in flagged and other not in flagged:
            per_axis[a].append((g, dx))
    return {a: (_weighted_median(g) if g else None) for a, g in per_axis.items()}


def _weighted_median(values: list[tuple[float, float]]) -> float:
    """The median of (value, weight) pairs: the mean of the two middle values where the weight splits exactly in
    half (so equal weights give statistics.median)."""
    ordered = sorted(values)
    half = sum(w for _, w in ordered) / 2.0
    cumulative = 0.0
    for i, (v, w) in enumerate(ordered):
        cumulative += w
        if math.isclose(cumulative, half, rel_tol=1e-12):
            return (v + ordered[i + 1][0]) / 2.0
        if cumulative > half:
            return v
    return ordered[-1][0]


# (the reference neighbours, their median theta, this cell's distance to it, the local change across it per axis
# in rad per unit): _fit's answer
Fitted = tuple[list[tuple[Key, str, float]], tuple[float, float] | None, float | None, dict[str, float]]


def _fit(
    key: Key,
    around: list[tuple[Key, str, float]],
    theta: dict[Key, tuple[float, float]],
    axis_values: list[list[float]],
    flagged: Container[Key],
) -> Fitted:
    """(the reference neighbours, the component-wise median of their theta with each pair across the
    cell centred on its interpolation at the cell's position, a lone neighbour on an axis extrapolated along the
    line to the next reference beyond it, this cell's distance to it)."""
    if len(around) < MIN_NEIGHBOURS:
        return around, None, None, {}
    values: list[tuple[float, float]] = []
    across: dict[str, float] = {}
    for pos, a in enumerate(AXES):
        on_axis = [(o, dx) for o, ax, dx in around if ax == a]
        below = [(o, dx) for o, dx in on_axis if o[pos] < key[pos]]
        above = [(o, dx) for o, dx in on_axis if o[pos] > key[pos]]
        if below and above:
            (lo, d_lo), (hi, d_hi) = below[0], above[0]
            # e.g. 1800 rpm between 1500 and 2000: w_lo = 2/5; the pair shifted by -(1/10) (theta_lo - theta_hi)
            k = d_hi / (d_lo + d_hi) - 0.5
            shift = (k * (theta[lo][0] - theta[hi][0]), k * (theta[lo][1] - theta[hi][1]))
            values += [(theta[o][0] + shift[0], theta[o][1] + shift[1]) for o in (lo, hi)]
            across[a] = math.hypot(theta[hi][0] - theta[lo][0], theta[hi][1] - theta[lo][1]) / (d_lo + d_hi)
        else:
            for o, dx in on_axis:
                # one side only (an axis end, or the other side not ok): the line through this neighbour and the next
                # one beyond it, at the cell; and the change per unit between them (neither is this cell, so a bad
                # cell does not excuse itself: at a turn, as at an axis end of a steep map, the map changes that fast)
                beyond = _next_along(o, pos, o[pos] - key[pos], axis_values[pos])
                span = abs(beyond[pos] - o[pos]) if beyond is not None else 0.0
                if beyond is None or beyond not in theta or beyond in flagged:
                    values.append(theta[o])  # no reference beyond: the neighbour as it is
                    continue
                across[a] = math.hypot(theta[o][0] - theta[beyond][0], theta[o][1] - theta[beyond][1]) / span
                if span < dx:
                    # one so close that the line would be extrapolated over more than its span (its noise amplified):
                    # the neighbour as it is, and the map's change there all the same (a refined map's last speed
                    # past the turn, 100 rpm beyond a pair 50 rpm apart, moves as fast as that pair does)
                    values.append(theta[o])
                    continue
                k = dx / span
                values.append(
                    (
                        theta[o][0] + k * (theta[o][0] - theta[beyond][0]),
                        theta[o][1] + k * (theta[o][1] - theta[beyond][1]),
                    )
                )
    fit = (statistics.median([v[0] for v in values]), statistics.median([v[1] for v in values]))
    value = theta[key]
    return around, fit, math.hypot(value[0] - fit[0], value[1] - fit[1]), across


def _next_along(o: Key, pos: int, direction: float, values: list[float]) -> Key | None:
    """The grid point one index beyond o along axis pos, away from the cell (direction: the sign of o - cell)."""
    i = values.index(o[pos]) + (1 if direction > 0 else -1)
    if not 0 <= i < len(values):
        return None
    moved = list(o)
    moved[pos] = values[i]
    return (moved[0], moved[1], moved[2])


def _evaluate(fitted: Fitted, gradients: dict[str, float | None]) -> CellQuality:
    around, fit, deviation, across = fitted
    neighbours = [o for o, _, _ in around]
    # per neighbour the step the map's median change predicts, or the change across the cell where theta* moves
    # faster here (the field-weakening turn, where a refinement puts its breakpoints close: a turn its two
    # neighbours agree on is a turn, not an outlier; one bad cell leaves its neighbours' change across it small)
    steps = [max(g, across.get(a, 0.0)) * dx for _, a, dx in around if (g := gradients[a]) is not None]
    if fit is None or not steps:
        return CellQuality("unchecked", neighbours=neighbours)
    expected = max(statistics.median(steps), math.radians(MIN_STEP_DEG))
    return CellQuality(
        "consistent", fit=fit, neighbours=neighbours, deviation_rad=deviation, expected_step_rad=expected
    )


def _reason(value: tuple[float, float], c: CellQuality, gradients: dict[str, float | None]) -> str:
    g_here, d_here = (math.degrees(x) for x in gamma_delta(*value))
    # a flagged cell was scored: it has a fit, a deviation and an expected step
    assert c.fit is not None and c.deviation_rad is not None and c.expected_step_rad is not None
    g_fit, d_fit = (math.degrees(x) for x in gamma_delta(*c.fit))
    per_axis = ", ".join(f"{math.degrees(g):.3g} deg per {AXIS_UNITS[a]}" for a, g in gradients.items() if g)
    return (
        f"theta {math.degrees(c.deviation_rad):.2f} deg from the median of its {len(c.neighbours)} ok neighbours, "
        f"{c.score:.1f}x the step expected to them ({math.degrees(c.expected_step_rad):.2f} deg from the map's "
        f"median theta change: {per_axis or 'none'}); here gamma {g_here:.2f} deg / delta {d_here:.1f} deg, "
        f"neighbours' median {g_fit:.2f} deg / {d_fit:.1f} deg: measure this point again or smooth the map"
    )


def smoothing(
    quality: MapQuality, map_id: int, result_ids: dict[Key, int | None]
) -> dict[Key, tuple[tuple[float, float], str]]:
    """The remedy for the outliers: each one's theta replaced by its neighbours' fit (the median of
    their estimates above, by position on the axes), with where the value comes from. Outliers without a fit (their neighbours were flagged
    too) keep their measured theta."""
    out = {}
    for key, c in quality.cells.items():
        if c.quality != "outlier" or c.fit is None:
            continue
        around = "; ".join(f"{o[0]:g} Nm / {o[1]:g} rpm / {o[2]:g} V" for o in c.neighbours)
        measured = f"result {result_ids.get(key)}" if result_ids.get(key) is not None else "the measured cell"
        out[key] = (
            c.fit,
            f"median theta of the ok neighbours of map {map_id} at {around}; the theta of {measured} is not used",
        )
    return out
