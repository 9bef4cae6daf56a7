"""A LUT's breakpoints placed from theta* curves measured on the bench (issue 27, point 4); the refinement (service/runs/kinds/refinement.py) runs its rounds: dense where theta* turns,
cheap elsewhere, along speed and along torque.

Why from curves and not from validations: the drive's LUT-mode suppression at a point is
20 log10 |theta*| / |theta_lut - theta*| (the residual is S (theta_lut - theta*), eq. 8, against the
uncompensated -S theta*), so what a validation would measure between two breakpoints is known as soon as
theta* is identified there: the drive's own interpolation (drivers.lut_image.between, Lut.theta's rule) of the two
neighbours against the identified theta* at the value between them. An identification costs 0.1-0.3 plant s
(tests/benchmarks/bench_identification.py) where a validation point costs a move, an uncompensated and a
LUT-mode window, and a run-up pair 2 x 16 s per torque.

Bisection, per axis (torque and speed; U_dc lines are left as they are):
  - a round's candidates are the midpoints of intervals not yet settled; each candidate is a whole line of
    cells (a LUT is a full grid), identified at every value of the other axes;
  - a candidate is judged by its worst cell: the interpolation of the candidate's two neighbours on its axis
    (the current axes, without the other candidates) against the identified theta* there, in dB as above;
  - a candidate short of target_db + PLACE_MARGIN_DB is kept (inserted into its axis) and both halves of its
    interval become the next round's candidates while they are at least MIN_STEP wide; a candidate that
    holds is dropped (its cells stay stored as evidence, outside the map) and its interval is settled, until
    the other axis gains values: then every interval of this axis is a candidate again, judged at those new
    values too (only cells not measured yet are measured: `cells_to_measure`);
  - kept candidates are taken while the LUT image fits `max_bytes`, those with the most cells short per byte
    of their line first (then the worst): what a byte of firmware memory buys.
The margin: a midpoint measures an interval's error where a smooth curve's is largest, but an identified
theta* carries its own error (identification stops at a margin below its target) and a turn may sit off the
midpoint; 6 dB (a factor 2 in the interpolation error) covers both in the run-ups measured.
Points with no evidence (a neighbour or the candidate not identified ok: outside the envelope, failed) do not
count; a candidate with none at all is dropped.
Why steps and not tracking along a slow ramp: the adaptive law's time constant is ~0.04 plant s (40 dB in
0.17 s, bench_identification), so on a ramp of r rpm/s it lags theta* by 0.04 r rpm; at the turn theta*
moves up to 6.5 deg/rpm and 30 dB asks for 1.8 deg, i.e. a lag under 0.28 rpm: r <= 7 rpm/s, 2 x 230 s per
torque over 1000..2600 rpm (up and down), where a 10 rpm step identified with its neighbour's prior costs
~0.2 s.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from itertools import product

import numpy as np

from drivers.lut_image import AXES, FLAG_NONE, FLAG_OK, SPARSE, along_row, between
from service.maps.lut_export import SPARSE_BAR_DB, image_bytes, stored_mask

PLACED_AXES = ("torque_nm", "speed_rpm")  # of AXES (the LUT's, torque, speed, U_dc): U_dc lines stay as they are
PLACE_MARGIN_DB = 6.0
# an interval is bisected only while its halves are at least this wide (the issue's <= 10 rpm where theta* turns)
MIN_STEP = {"torque_nm": 0.125, "speed_rpm": 10.0}
MAX_PLACE_ROUNDS = 8

Cell = tuple[float, float, float]  # (torque_nm, speed_rpm, udc_v)


def midpoints(values: list[float], axis: str) -> list[float]:
    """The midpoint of each interval of `values` whose halves are at least MIN_STEP[axis] wide."""
    v = sorted(values)
    return [round((a + b) / 2.0, 6) for a, b in zip(v, v[1:]) if (b - a) / 2.0 >= MIN_STEP[axis] - 1e-9]


def first_candidates(axes: dict[str, list[float]]) -> dict[str, list[float]]:
    """Round one: the midpoint of every interval of the placed axes."""
    return {a: midpoints(axes[a], a) for a in PLACED_AXES}


def axes_with(axes: dict[str, list[float]], inserted: dict[str, list[float]]) -> dict[str, list[float]]:
    """The axes with the values `inserted` per axis added (sorted, each value once)."""
    return {a: sorted(set(map(float, axes[a])) | set(inserted.get(a, []))) for a in AXES}


def candidate_cells(axes: dict[str, list[float]], candidates: dict[str, list[float]]) -> list[Cell]:
    """The cells the candidates' lines add to the full grid of `axes` (cross cells of two candidates included)."""
    grown = axes_with(axes, candidates)
    old = set(product(*(map(float, axes[a]) for a in AXES)))
    return [(t, n, u) for t, n, u in product(*(map(float, grown[a]) for a in AXES)) if (t, n, u) not in old]


def predicted_db(theta_true: complex, theta_lut: complex) -> float:
    """LUT-mode suppression where the drive injects theta_lut and theta* is theta_true (module doc), dB."""
    error = abs(theta_lut - theta_true)
    if error == 0.0:
        return math.inf
    return 20.0 * math.log10(abs(theta_true) / error) if theta_true != 0 else -math.inf


def _lines(axes: dict[str, list[float]], axis: str) -> Iterator[Callable[[float], Cell]]:
    """Each line of `axis` through the grid `axes` (the other axes' values fixed), as the cell at a value on it."""
    k = AXES.index(axis)
    for rest in product(*(sorted(map(float, axes[a])) for a in AXES if a != axis)):

        def at(x: float, rest: tuple[float, ...] = rest) -> Cell:
            cell = list(rest)
            cell.insert(k, x)
            return (cell[0], cell[1], cell[2])

        yield at


def judge_candidates(
    axes: dict[str, list[float]],
    candidates: dict[str, list[float]],
    thetas: dict[Cell, complex],
    interpolation: str,
) -> dict[str, dict[float, list[float]]]:
    """Each candidate's predicted suppression at every cell of its line with evidence (dB; an empty list: none),
    per axis."""
    out: dict[str, dict[float, list[float]]] = {}
    for axis in PLACED_AXES:
        values = sorted(map(float, axes[axis]))
        out[axis] = {}
        for c in candidates.get(axis, []):
            lower = [v for v in values if v < c]
            upper = [v for v in values if v > c]
            out[axis][c] = []
            if not lower or not upper:
                continue
            a, b = lower[-1], upper[0]
            for at in _lines(axes, axis):
                ta, tb, tc = thetas.get(at(a)), thetas.get(at(b)), thetas.get(at(c))
                if ta is None or tb is None or tc is None:
                    continue
                if interpolation == "cubic":  # the corners' slopes from their neighbours on this axis
                    lut = along_row(values, [thetas.get(at(v)) for v in values], c, interpolation)
                else:
                    lut = between(ta, tb, a, b, c, interpolation)
                out[axis][c].append(predicted_db(tc, lut))
    return out


def bend_db(
    axes: dict[str, list[float]], candidates: dict[str, list[float]], thetas: dict[Cell, complex]
) -> dict[str, dict[float, float]]:
    """Each candidate's need before its line is measured, per axis (dB; lower: more need): over the lines of its
    axis with evidence, the worst of predicted_db(cubic, chord), the cubic Hermite through the grid's theta* (each
    corner's slope from its neighbours) against the chord between the candidate's two neighbours at the candidate's
    value. The two interpolants differ by h^2/8 of the curve's second derivative at an interval's middle (and agree
    where theta* runs straight): where theta* bends on the grid's breakpoints, the drive's interpolation is the least
    sure. inf: no evidence (an axis end, a neighbour not identified), nothing seen to bend."""
    out: dict[str, dict[float, float]] = {}
    for axis in PLACED_AXES:
        values = sorted(map(float, axes[axis]))
        out[axis] = {}
        for c in candidates.get(axis, []):
            worst = math.inf
            for at in _lines(axes, axis):
                row = [thetas.get(at(v)) for v in values]
                j = sum(1 for v in values if v < c) - 1
                if j < 0 or j + 1 >= len(values):
                    continue
                a, b = row[j], row[j + 1]
                if a is None or b is None:
                    continue
                chord = between(a, b, values[j], values[j + 1], c, "cartesian")
                worst = min(worst, predicted_db(along_row(values, row, c, "cubic"), chord))
            out[axis][c] = worst
    return out


def worst_db(judged: dict[str, dict[float, list[float]]]) -> dict[str, float | None]:
    """Per axis, the worst predicted suppression over every candidate's line (None: no evidence)."""
    return {axis: min((db for dbs in by.values() for db in dbs), default=None) for axis, by in judged.items()}


def _stored_cells(axes: dict[str, list[float]], thetas: dict[Cell, complex], interpolation: str) -> int:
    """Cells a version 7 image of the grid `axes` stores with the identified theta* `thetas` (service/maps/lut_export.py
    stored_mask, the encoder's walk; a cell not identified has no entry there: stored)."""
    shape = tuple(len(axes[a]) for a in reversed(AXES))  # [udc][speed][torque]
    theta = np.zeros(shape, dtype=complex)
    flags = np.full(shape, FLAG_NONE)
    for (iu, u), (i_n, n), (it, t) in product(*(enumerate(map(float, sorted(axes[a]))) for a in reversed(AXES))):
        if (t, n, u) in thetas:
            theta[iu, i_n, it], flags[iu, i_n, it] = thetas[(t, n, u)], FLAG_OK
    speeds = sorted(map(float, axes["speed_rpm"]))
    return int(stored_mask(speeds, theta.real, theta.imag, flags, SPARSE_BAR_DB, interpolation).sum())


def grid_bytes(
    axes: dict[str, list[float]], thetas: dict[Cell, complex], lut_cells: str, interpolation: str = "polar"
) -> int:
    """Bytes of the LUT image of the grid `axes` with the identified theta* `thetas` (a cell not identified counts as
    stored): image_bytes, with the cells a version 7 image stores."""
    if lut_cells != SPARSE:
        return image_bytes(axes, lut_cells)
    return image_bytes(axes, lut_cells, _stored_cells(axes, thetas, interpolation))


def _line_bytes(
    axes: dict[str, list[float]],
    axis: str,
    value: float,
    n_short: int,
    thetas: dict[Cell, complex],
    lut_cells: str,
    interpolation: str,
) -> int:
    """What a candidate's line adds to the image. A version 7 image: the axis value and the bitmap's bits, and a
    speed value's cells only in the rows where it is short (elsewhere the row's interpolation holds it: it is
    left out), a torque row's the cells its own row stores."""
    grown = axes_with(axes, {axis: [value]})
    if lut_cells != SPARSE:
        return image_bytes(grown, lut_cells) - image_bytes(axes, lut_cells)
    cells = n_short if axis == "speed_rpm" else _stored_cells({**axes, axis: [value]}, thetas, interpolation)
    return image_bytes(grown, lut_cells, cells) - image_bytes(axes, lut_cells, 0)


def place(
    axes: dict[str, list[float]],
    judged: dict[str, dict[float, list[float]]],
    target_db: float,
    max_bytes: int | None,
    lut_cells: str = "float32",
    thetas: dict[Cell, complex] | None = None,
    interpolation: str = "polar",
    affordable: Callable[[dict[str, list[float]]], str | None] | None = None,
) -> tuple[dict[str, list[float]], dict[str, list[float]], list[str]]:
    """(kept values per axis, the next round's candidates, reasons for what was left out): candidates with a cell
    short of target_db + PLACE_MARGIN_DB are kept while the image fits max_bytes (and `affordable(axes)`, what the
    grid with them would cost in another budget, says nothing against them), those with the most short cells
    per byte of their line first (a full grid: a torque row costs a cell per speed value; a version 7 image: a
    speed value costs a cell only in the rows where it is short, `_line_bytes`), then the worst; the next
    candidates are the midpoints of the kept values' two halves. lut_cells: the image's cell format (bytes);
    thetas: theta* identified per cell (what a version 7 image stores depends on it)."""
    bar = target_db + PLACE_MARGIN_DB
    thetas = thetas or {}
    base = grid_bytes(axes, thetas, lut_cells, interpolation)
    short = []
    for axis, by_value in judged.items():
        for c, dbs in by_value.items():
            n_short = sum(1 for db in dbs if db < bar)
            if n_short:
                line_bytes = _line_bytes(axes, axis, c, n_short, thetas, lut_cells, interpolation)
                short.append((-n_short / line_bytes, min(dbs), axis, c, line_bytes))
    kept: dict[str, list[float]] = {a: [] for a in PLACED_AXES}
    reasons: list[str] = []
    spent = 0
    for _per_byte, db, axis, c, line_bytes in sorted(short):
        if lut_cells == SPARSE:
            size = base + spent + line_bytes
        else:
            size = image_bytes(axes_with(axes, {**kept, axis: [*kept[axis], c]}), lut_cells)
        if max_bytes is not None and size > max_bytes:
            reasons.append(f"{axis} {c:g} (predicted {db:.1f} dB) left out: the LUT would exceed {max_bytes} bytes")
            continue
        against = None if affordable is None else affordable(axes_with(axes, {**kept, axis: [*kept[axis], c]}))
        if against is not None:
            reasons.append(f"{axis} {c:g} (predicted {db:.1f} dB) left out: {against}")
            continue
        kept[axis].append(c)
        spent += line_bytes
    nxt: dict[str, list[float]] = {a: [] for a in PLACED_AXES}
    grown = axes_with(axes, kept)
    for axis in PLACED_AXES:
        values = sorted(map(float, axes[axis]))
        for c in kept[axis]:
            a = max(v for v in values if v < c)
            b = min(v for v in values if v > c)
            nxt[axis] += midpoints([a, c, b], axis)
        if any(kept[other] for other in PLACED_AXES if other != axis):
            # an interval settled on the other axis's old values was never judged at its new ones (paper-bench:
            # 3.5 Nm held at the first 5 speeds and missed 20-29 dB at the turn's): every interval again there
            nxt[axis] += midpoints(grown[axis], axis)
        nxt[axis] = sorted(set(nxt[axis]))
    return {a: sorted(v) for a, v in kept.items()}, nxt, reasons


def cells_to_measure(
    axes: dict[str, list[float]], candidates: dict[str, list[float]], measured: set[Cell]
) -> list[Cell]:
    """The next round's cells: every cell of `axes` (the grid with this round's kept values) not measured yet,
    and the candidates' lines where they are not: a candidate is judged at the cells of its line on `axes`
    (judge_candidates), so the crossing of two candidates on different axes waits until both are kept."""
    grid: set[Cell] = {(t, n, u) for t, n, u in product(*(map(float, axes[a]) for a in AXES))}
    lines = {
        cell
        for cell in candidate_cells(axes, candidates)
        if sum(cell[AXES.index(a)] in candidates.get(a, []) for a in PLACED_AXES) <= 1  # not a crossing
    }
    return sorted(c for c in grid | lines if c not in measured)
