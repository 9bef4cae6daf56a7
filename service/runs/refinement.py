"""Refining a map on the drive until its LUT holds: what to measure next, from a validation in LUT mode.

A refinement (POST /maps/{id}/refine) runs in rounds, each: validate the current map in the drive's own
LUT mode (service/runs/validation.py: every grid point and every midpoint between neighbouring grid
values); where a point misses `target_db`, plan what to add; identify the new cells (priors from their
neighbours); build the refined map; validate again. It ends when every validated point holds, or when
the budget (`max_cells` cells identified in all) cannot pay for what is needed.

What a failing point asks for (`plan_round`):
- a grid point (a cell of the map) whose LUT entry misses the target at the cell itself: the cell is
  identified again (its entry was not good enough; a filled or non-ok cell first of all);
- a midpoint: the LUT's interpolation between cells misses the target there. The value of the failing
  coordinate is inserted into its axis: on the axis where the point lies between two grid values and the
  neighbouring cells' theta differs most (that is where the interpolation error comes from); a midpoint
  between values on several axes inserts on the one with the largest theta step. An inserted value
  adds a whole line of cells (the other axes' lengths multiplied: a LUT is a full grid).
Each candidate (a re-measured cell, an inserted value) is scored by the failing points it serves per
cell it costs (the refinement is judged by how many points hold), ties broken by the dB they are short
of the target (each capped at MAX_SHORT_DB). A round takes the candidates in order
of score while the budget lasts and their score is at least ROUND_SCORE_FRACTION of the best: what is
far off is fixed first, and the budget is kept for what the next validation shows (an inserted value
makes new midpoints, which may need more). The axes stay strictly increasing and may be non-uniform
(every export and the LUT image carry each axis' own breakpoints).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import product
from typing import TYPE_CHECKING, Annotated, Any, Literal, Mapping, NotRequired, TypedDict

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, model_validator

from service.identification.registry import METHODS
from service.maps.lut_export import SPARSE, Interpolation, image_bytes
from service.maps.placement import grid_bytes
from service.names import MAX_NAME_LENGTH, check_name
from service.runs.runup_validation import is_harm

if TYPE_CHECKING:  # validation.py runs the items; this module only reads them
    from service.runs.validation import ValidationItem
    from service.settings import Settings
from service.runs.validation import ValidationOptions, validation_items

AXES = ("torque_nm", "speed_rpm", "udc_v")
MAX_ROUNDS = 8  # a refinement that has not converged in this many rounds stops and says so
MAX_SHORT_DB = 30.0  # a point's claim on the budget: how far it is below the target, at most this
ROUND_SCORE_FRACTION = 0.25
RUNUP_STRETCH_GAP_RPM = 25.0  # failing run-up bins this close (2 bins missing at 10 rpm) are one stretch
MERGE_INSERT_RPM = 20.0  # a speed inserted this close to another candidate of the round joins it

Cell = tuple[float, float, float]  # a cell's (torque_nm, speed_rpm, udc_v), the order of AXES


# the drive's interpolation a refinement places and validates in unless its request or its source map names one: cubic
# along speed, as its maps are dense where theta* turns (a loop past the field-weakening onset, which chords cut).
# Measured (tests/benchmarks/bench_runup_refinement.py, int11 cells, 2048 bytes, run-ups at 7 torques): points and
# bins held cubic / polar 99.0 / 96.3 % (paper-bench), 99.2 / 95.8 % (seed 5), the worst 6.6 / -8.8 dB with no cell
# turned off. A coarse map stays polar (DEFAULT_INTERPOLATION): seed 5's 4 x 5 probe map holds 431 of 1161 points
# cubic against 523 polar (a cubic through breakpoints 400 rpm apart overshoots the loop).
REFINED_INTERPOLATION: Interpolation = "cubic"


class RefineRequest(BaseModel):
    """POST /maps/{id}/refine. Every field bounded."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    # printable text as every name (service/names.py): a NUL or a newline is a 422, not a bench nobody serves
    bench: Annotated[str, AfterValidator(lambda v: check_name(v, "bench name"))] | None = Field(
        None,
        min_length=1,
        max_length=MAX_NAME_LENGTH,
        description="the bench it runs on; default this service's own bench. Printable text: no control "
        "characters, no whitespace at either end",
    )
    target_db: float = Field(
        30.0,
        ge=0,
        le=80,
        description="LUT-mode suppression wanted at every validated point (grid points and midpoints), dB",
    )
    max_cells: int = Field(
        40,
        ge=1,
        le=2000,
        description="most cells the refinement identifies in all (re-measured and new cells): its bench-time budget",
    )
    max_bytes: int = Field(
        2048,
        ge=64,
        le=1 << 20,
        description="largest LUT image the refinement may build, bytes of firmware memory (header, axes, 9 bytes a "
        "cell; 5 with lut_cells int16)",
    )
    max_bench_s: float | None = Field(
        None,
        gt=0,
        le=7 * 24 * 3600,
        description="bench time the refinement may spend (plant seconds of its measurements and validations, each "
        "point's settling counted), spent ahead: no value is inserted and no round started whose cells and "
        "validation would not fit by the predicted cost (BenchBudget); the guard's round, which turns injection off "
        "where the LUT made things worse, runs regardless. None: no limit beyond max_cells",
    )
    method: str = Field("probe", description="identification method of the new cells (GET /methods)")
    options: dict[str, Any] = Field(default_factory=dict, description="the method's options (as for a sweep)")
    validation: ValidationOptions = Field(
        default_factory=ValidationOptions, description="how finely each validation point is measured"
    )
    lut_cells: Literal["float32", "int16", "int11", "int11-sparse"] = Field(
        "float32",
        description="how the refined LUT carries theta per cell: float32 (9 bytes a cell, image version 3/4), "
        "int16 (5 bytes a cell, image version 5, theta = q x one quantum: the largest component / 32767) or int11 "
        "(3 bytes a cell, image version 6: two 11-bit integers and the flag in 24 bits, quantum the largest "
        "component / 1023) or int11-sparse (image version 7: int11 cells stored only where the drive cannot interpolate them "
        "from their row along speed within 36 dB, one bit a cell says which: per-row speed breakpoints); max_bytes "
        "counts that format, and the refined map's downloads and exports use it",
    )
    placement: Literal["curves", "validation"] = Field(
        "curves",
        description="curves: first place breakpoints from theta* identified between them (bisection along torque "
        "and speed, service/maps/placement.py), then validate; validation: insert only where a validation fails",
    )

    @model_validator(mode="after")
    def _cubic_takes_every_cell(self) -> RefineRequest:
        if self.lut_cells == SPARSE and self.validation.interpolation == "cubic":
            raise ValueError(
                "validation.interpolation cubic takes every cell of a row (each corner's slope from its neighbours): "
                "lut_cells int11-sparse derives cells from two stored ones; use int11, int16 or float32"
            )
        return self


class RefinementState(TypedDict):
    """Where a refinement stands, saved after every step in its sweep's `refinement` column (so a resume goes
    on from there): service/runs/kinds/refinement.py runs the rounds."""

    target_db: float
    max_cells: int
    validation: dict[str, Any]  # the ValidationOptions of its validations, dumped
    phase: str  # measure | validate | done
    round: int
    current_map_id: int  # the map the rounds have built so far (the source map before the first)
    axes: dict[str, list[float]]  # the current map's axes, with the values inserted so far
    pending: list[list[float]]  # the round's cells to identify, [torque_nm, speed_rpm, udc_v] each
    cells_added: int  # cells identified in the rounds so far (the budget spent)
    rounds: list[dict[str, Any]]  # each round's validation figures
    stopped: str | None  # why it stopped short of the target (None: it holds, or it goes on), in one line
    stopped_details: NotRequired[list[str]]  # each candidate the last plan left out, and why
    max_bytes: NotRequired[int]  # (a state saved before budgets in bytes and bench time has neither)
    max_bench_s: NotRequired[float | None]
    plant_time_s: NotRequired[float]  # bench seconds spent in all rounds so far (plant time, each point's settling too)
    round_plant_s: NotRequired[float]  # of the round in progress: its cells' settling and measurements
    guard_off: NotRequired[list[list[float]]]  # cells given injection off where the LUT made things worse
    guard_rounds: NotRequired[int]
    candidates: NotRequired[dict[str, list[float]]]  # placement from curves: the round's candidate values per axis
    lut_cells: NotRequired[str]  # float32 | int16: the refined maps' LUT cells (max_bytes counts them)
    placement_rounds: NotRequired[list[dict[str, Any]]]  # each placement round's candidates, what it kept, its cost


@dataclass
class RoundPlan:
    """What one round adds: values per axis, and the cells to identify (new ones and re-measured ones)."""

    inserted: dict[str, list[float]] = field(default_factory=dict)
    remeasure: list[Cell] = field(default_factory=list)
    new_cells: list[Cell] = field(default_factory=list)
    failing: int = 0
    reasons: list[str] = field(default_factory=list)  # each candidate left out, and why (one line each)
    # the same grouped, for a verdict a person reads in one line: axis -> values left out
    over_cells: dict[str, list[float]] = field(default_factory=dict)  # needing more cells than were left
    cells_left: int | None = None  # ... the fewest cells left when one was
    over_bytes: dict[str, list[float]] = field(default_factory=dict)  # making the LUT larger than max_bytes
    crossings_over: bool = False

    @property
    def cells(self) -> list[Cell]:
        return self.remeasure + self.new_cells

    def why_nothing_fits(self, max_bytes: int | None) -> str:
        """Why the plan inserts nothing more, in one short clause per cause."""
        causes = []
        if self.over_cells:
            causes.append(
                f"inserting {_values_listed(self.over_cells)} needs more cells than the {self.cells_left} left"
            )
        if self.over_bytes:
            causes.append(
                f"inserting {_values_listed(self.over_bytes)} makes the LUT larger than max_bytes = {max_bytes}"
            )
        if self.crossings_over:
            causes.append("the crossings of the inserted values exceed the budget")
        return "; ".join(causes) or "nothing left to insert"


def _values_listed(values: dict[str, list[float]], most: int = 3) -> str:
    """{"speed_rpm": [2290, 2350, 2410, 2470]} -> "speed_rpm 2290, 2350, 2410 (and 1 more)"."""
    parts = []
    for axis, vals in values.items():
        shown = ", ".join(f"{v:g}" for v in sorted(vals)[:most])
        parts.append(f"{axis} {shown}" + (f" (and {len(vals) - most} more)" if len(vals) > most else ""))
    return " and ".join(parts)


@dataclass(frozen=True)
class _Remeasure:
    """A candidate of a round: a grid cell identified again."""

    shorts: list[float]  # dB short of the target, of each failing point it serves
    cell: Cell
    cost: int = 1


@dataclass(frozen=True)
class _Insert:
    """A candidate of a round: a value inserted into an axis (a whole line of cells)."""

    shorts: list[float]  # dB short of the target, of each failing point it serves
    axis: str
    value: float
    cost: int  # cells of the line, with the axes as they are


def _cell_of(values: Mapping[str, Any]) -> Cell:
    return (float(values["torque_nm"]), float(values["speed_rpm"]), float(values["udc_v"]))


def failing_points(cells: list[dict[str, Any]], target_db: float) -> list[dict[str, Any]]:
    """Validation cells that miss the target: judged as not holding (a run-up bin: by the target or the floor
    rule, service/runs/runup_validation.py), measured below it, or not measured at all (failed)."""
    return [
        c
        for c in cells
        if c["status"] != "measured"
        or c["suppression_db"] is None
        or (not c["holds"] if c.get("holds") is not None else c["suppression_db"] < target_db)
    ]


def _runup_claims(failing: list[dict[str, Any]]) -> list[tuple[dict[str, Any], int]]:
    """Failing run-up bins as claims: per torque and U_dc, each stretch of adjacent failing bins is one claim at
    its worst bin, serving every bin of the stretch (an inserted breakpoint fixes a stretch, not a bin)."""
    by_row: dict[tuple[float, float], list[dict[str, Any]]] = {}
    for c in failing:
        op = c["operating_point"]
        by_row.setdefault((float(op["torque_nm"]), float(op["udc_v"])), []).append(c)
    claims = []
    for bins in by_row.values():
        bins.sort(key=lambda c: c["operating_point"]["speed_rpm"])
        stretches = [[bins[0]]]
        for c in bins[1:]:
            gap = c["operating_point"]["speed_rpm"] - stretches[-1][-1]["operating_point"]["speed_rpm"]
            if gap <= RUNUP_STRETCH_GAP_RPM:
                stretches[-1].append(c)
            else:
                stretches.append([c])
        for stretch in stretches:
            worst = min(stretch, key=lambda b: b["suppression_db"] if b["suppression_db"] is not None else -math.inf)
            claims.append((worst, len(stretch)))
    return claims


def _theta_at(map_cells: dict[Cell, dict[str, Any]], key: Cell) -> tuple[float, float] | None:
    c = map_cells.get(key)
    if c is None or c.get("theta_cos") is None:
        return None
    return float(c["theta_cos"]), float(c["theta_sin"])


def _neighbours(values: list[float], x: float) -> tuple[float, float] | None:
    below = [v for v in values if v < x]
    above = [v for v in values if v > x]
    return (max(below), min(above)) if below and above else None


def plan_round(
    axes: dict[str, list[float]],
    map_cells: list[dict[str, Any]],
    validation_cells: list[dict[str, Any]],
    target_db: float,
    budget_cells: int,
    max_bytes: int | None = None,
    lut_cells: str = "float32",
) -> RoundPlan:
    """The next round's cells (module doc). map_cells: the current map's cells (MapCellPublic dumps);
    validation_cells: its validation's cells. Raises nothing: an empty plan means nothing is left to
    do, or nothing fits the budget (`reasons` says which)."""
    plan = RoundPlan()
    by_key = {_cell_of(c): c for c in map_cells}
    failing = failing_points(validation_cells, target_db)
    plan.failing = len(failing)
    if not failing:
        return plan
    grid_values = {a: sorted(float(v) for v in axes[a]) for a in AXES}
    remeasure: dict[Cell, list[float]] = {}
    insertions: dict[tuple[str, float], list[float]] = {}  # (axis, value) -> dB short of each point served
    rows_touched: dict[tuple[str, float], set[float]] = {}  # (axis, value) -> the torque rows its points lie between
    claims = [(c, 1) for c in failing if c["kind"] != "runup"]
    claims += _runup_claims([c for c in failing if c["kind"] == "runup"])
    for c, serves in claims:
        op = c["operating_point"]
        key = _cell_of(op)
        measured_db = c["suppression_db"] if c.get("suppression_db") is not None else -math.inf
        short_db = min(MAX_SHORT_DB, target_db - measured_db)
        if c["kind"] == "grid":
            remeasure.setdefault(key, []).append(short_db)
            continue
        best: tuple[float, str, float] | None = None  # (theta step, axis, value)
        for i, axis in enumerate(AXES):
            if key[i] in grid_values[axis]:
                continue
            sides = _neighbours(grid_values[axis], key[i])
            if sides is None:
                continue
            lo, hi = (list(key), list(key))
            lo[i], hi[i] = sides
            # the neighbouring cells along this axis, at the grid values of the other coordinates nearest the point
            step = _theta_step(by_key, grid_values, lo, hi, i)
            if best is None or step > best[0]:
                best = (step, axis, key[i])
        if best is not None:
            _, axis, value = best
            near = [
                v for a, v in insertions if a == axis and abs(v - value) <= MERGE_INSERT_RPM and axis == "speed_rpm"
            ]
            insertions.setdefault((axis, near[0] if near else value), []).extend([short_db] * serves)
            rows_touched.setdefault((axis, near[0] if near else value), set()).update(
                corner_values(grid_values["torque_nm"], key[0])
            )
    # candidates by failing points served per cell they cost, then by the dB they are short
    sizes = {a: len(grid_values[a]) for a in AXES}
    candidates: list[_Remeasure | _Insert] = [_Remeasure(shorts, key) for key, shorts in remeasure.items()]
    for (axis, value), shorts in insertions.items():
        candidates.append(_Insert(shorts, axis, value, math.prod(n for a, n in sizes.items() if a != axis)))
    candidates.sort(key=lambda c: (-len(c.shorts) / c.cost, -sum(c.shorts) / c.cost, c.cost))
    left = budget_cells
    chosen_axes = {a: list(grid_values[a]) for a in AXES}
    # a version 7 image: what it stores now, and per insertion an estimate (a speed value stored in the rows its
    # failing points lie between, a torque row half its speed values); lut_export.lut_image keeps the image in
    # max_bytes whatever the estimate missed
    sparse_bytes = (
        grid_bytes(axes, {k: complex(*t) for k in by_key if (t := _theta_at(by_key, k)) is not None}, SPARSE)
        if lut_cells == SPARSE
        else 0
    )
    best_score = len(candidates[0].shorts) / candidates[0].cost if candidates else 0.0
    for candidate in candidates:
        if len(candidate.shorts) / candidate.cost < ROUND_SCORE_FRACTION * best_score:
            break  # the rest waits for the next validation
        if isinstance(candidate, _Remeasure):
            if left >= 1:
                plan.remeasure.append(candidate.cell)
                left -= 1
            continue
        axis, value = candidate.axis, candidate.value
        # cost with the values inserted so far on the other axes
        cost = math.prod(len(chosen_axes[a]) for a in AXES if a != axis)
        if cost > left:
            plan.reasons.append(f"inserting {axis} = {value:g} needs {cost} cells, {left} left in the budget")
            plan.over_cells.setdefault(axis, []).append(value)
            plan.cells_left = left if plan.cells_left is None else min(plan.cells_left, left)
            continue
        grown = {**chosen_axes, axis: sorted(set(chosen_axes[axis]) | {value})}
        if lut_cells == SPARSE:
            rows = (
                len(rows_touched.get((axis, value), ())) if axis == "speed_rpm" else len(chosen_axes["speed_rpm"]) // 2
            )
            size = sparse_bytes + image_bytes(grown, SPARSE, max(rows, 1)) - image_bytes(chosen_axes, SPARSE, 0)
        else:
            size = image_bytes(grown, lut_cells)
        if max_bytes is not None and size > max_bytes:
            plan.reasons.append(
                f"inserting {axis} = {value:g} makes the LUT {size} bytes, over max_bytes = {max_bytes}"
            )
            plan.over_bytes.setdefault(axis, []).append(value)
            continue
        chosen_axes[axis] = grown[axis]
        sparse_bytes = size if lut_cells == SPARSE else 0
        plan.inserted.setdefault(axis, []).append(value)
        left -= cost
    # the new grid's cells that do not exist yet (a value inserted on two axes adds their crossing once)
    existing = set(by_key)
    plan.new_cells = [
        (t, n, u)
        for u, n, t in product(chosen_axes["udc_v"], chosen_axes["speed_rpm"], chosen_axes["torque_nm"])
        if (t, n, u) not in existing
    ]
    if len(plan.new_cells) + len(plan.remeasure) > budget_cells:  # crossings of two insertions
        plan.reasons.append("the crossings of the inserted values exceed the budget")
        plan.crossings_over = True
        plan.inserted, plan.new_cells = {}, []
    for axis in plan.inserted:
        plan.inserted[axis].sort()
    return plan


def _theta_step(
    by_key: dict[Cell, dict[str, Any]],
    grid_values: dict[str, list[float]],
    lo: list[float],
    hi: list[float],
    axis_index: int,
) -> float:
    """|delta theta| between the two cells on either side along one axis, their other coordinates taken
    at the nearest grid values (a midpoint's other coordinates may be midpoints too); 0 if unknown."""

    def snap(key: list[float]) -> Cell:
        out = []
        for i, a in enumerate(AXES):
            if i == axis_index or key[i] in grid_values[a]:
                out.append(key[i])
            else:
                out.append(min(grid_values[a], key=lambda v: abs(v - key[i])))
        return out[0], out[1], out[2]

    a, b = _theta_at(by_key, snap(lo)), _theta_at(by_key, snap(hi))
    if a is None or b is None:
        return 0.0
    return math.hypot(a[0] - b[0], a[1] - b[1])


def check_request(request: RefineRequest) -> None:
    if request.method not in METHODS:
        raise ValueError(f"method {request.method!r} is not available; choose one of {sorted(METHODS)}")


MAX_GUARD_ROUNDS = 3  # injection turned off where harm is seen, validated again, at most this often


def harmful_points(cells: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Judged points (grid, midpoints, run-up bins) where the LUT makes the order worse than no compensation
    (service/runs/runup_validation.py is_harm)."""
    return [
        c
        for c in cells
        if c["status"] == "measured"
        and is_harm(c.get("suppression_db"), c.get("above_floor_db"), bool(c.get("no_injection")))
    ]


def corner_values(values: list[float], x: float) -> list[float]:
    """The breakpoints of an axis with a non-zero weight in the drive's interpolation at x (clamped at the ends)."""
    x = min(max(x, values[0]), values[-1])
    return [x] if x in values else list(_neighbours(values, x) or (x,))


# What bench time costs before this refinement measured it, plant s: a cell identified (its move, settling and
# windows; measured on the refinement's own placement rounds once one ran), a stepped validation point (its move,
# settling, the uncompensated and the LUT-mode window; measured by each validation for the next: `point_cost_s`) and a
# run-up beyond its ramp (the move to its start, the settling there). Measured on issue 27's calibrations (int11,
# ~600 cells, run-ups at 7 torques at 100 rpm/s, floor 45 dB): placement rounds 0.35-0.65 s a cell; a validation point
# 0.153-0.213 s at speedup 0 (paper-bench to seed 5, whose shaft settles longer), 0.170-0.231 s at speedup 1. Nothing
# measured before the first validation predicts its points: their cost over the placement cells' mean settling ranged
# 1.06-1.74 (machine and clock), and the source map's own validation, 200 rpm apart, settles longer (0.214 / 0.248 s a
# point against 0.155 / 0.213 s on the refined maps); so its points are taken at the middle of the range measured
CELL_S = 0.5
VALIDATION_POINT_S = 0.2
RUNUP_APPROACH_S = 3.0
# a round after a validation measures its cells again and the validation points around them, and runs the run-up
# pairs whose LUT changed again (measured: 112-121 s for 20 cells at the turn)
REVALIDATED_POINTS_PER_CELL = 8
REVALIDATED_RUNUP_PAIRS = 2


@dataclass(frozen=True)
class BenchBudget:
    """max_bench_s spent ahead (what the user pays): what is spent, what a cell costs, and what a validation of a
    grid would (its points and run-up pairs, `validation_items`), so a refinement inserts no value whose cells and
    validation would not fit, rather than finding out after the round that spent it."""

    max_bench_s: float
    spent_s: float
    cell_s: float
    settings: Settings
    options: ValidationOptions
    point_s: float = VALIDATION_POINT_S  # a stepped validation point, plant s (point_cost_s where one was measured)

    def validation_s(self, axes: dict[str, list[float]]) -> float:
        """Predicted plant time of one validation of the grid `axes` (every point and run-up pair measured)."""
        cost = 0.0
        for item in validation_items(axes, self.settings, self.options):
            if item.not_run is not None:
                continue
            if item.kind == "runup" and item.speed_range is not None:
                cost += self.runup_pair_s(item.speed_range[1] - item.speed_range[0])
            elif item.kind != "runup":
                cost += self.point_s
        return cost

    def runup_pair_s(self, span_rpm: float) -> float:
        """A run-up pair over `span_rpm`: two ramps at the validation's rate, each with its approach."""
        return 2 * (span_rpm / self.options.runup_rate_rpm_per_s + RUNUP_APPROACH_S)

    def against(self, cells: int, axes: dict[str, list[float]]) -> str | None:
        """Why measuring `cells` more and validating the grid `axes` does not fit the budget (None: it does)."""
        need_s = cells * self.cell_s + self.validation_s(axes)
        if self.spent_s + need_s <= self.max_bench_s:
            return None
        return (
            f"the bench time budget (max_bench_s = {self.max_bench_s:g} s, {self.spent_s:.0f} s spent) would not "
            f"hold its {cells} cell(s) and the validation ({need_s:.0f} s predicted)"
        )

    def against_round(self, cells: int, axes: dict[str, list[float]]) -> str | None:
        """Why a round after a validation of the grid `axes`, measuring `cells` again, does not fit the budget (None:
        it does)."""
        runups_s = 0.0
        if self.options.runups:
            runups_s = REVALIDATED_RUNUP_PAIRS * self.runup_pair_s(max(axes["speed_rpm"]) - min(axes["speed_rpm"]))
        need_s = cells * (self.cell_s + REVALIDATED_POINTS_PER_CELL * self.point_s) + runups_s
        if self.spent_s + need_s <= self.max_bench_s:
            return None
        return (
            f"the bench time budget (max_bench_s = {self.max_bench_s:g} s) is spent: {self.spent_s:.0f} s, and "
            f"another round of {cells} cell(s) would take ~{need_s:.0f} s"
        )


def point_cost_s(cells: list[dict[str, Any]]) -> float | None:
    """What a stepped validation point cost on this bench, plant s: the mean settling and windows of the points a
    validation measured itself (not taken from an earlier one, not a run-up's bins); None: it measured none."""
    costs = [
        float(c.get("plant_time_s") or 0.0) + float(c.get("settle_plant_s") or 0.0)
        for c in cells
        if c["kind"] != "runup" and c.get("status") == "measured" and not c.get("reused")
    ]
    return sum(costs) / len(costs) if costs else None


def no_progress(rounds: list[dict[str, Any]]) -> str | None:
    """Why a refinement ends for want of progress, or None: the round before the last only measured cells again
    (it inserted no axis value) and the last validation holds no more points than the one before it; more such
    rounds spend bench time for nothing (measured: seed 5 ran three at 388-451 plant s each, held 3137, 3135, 3136)."""
    if len(rounds) < 2 or rounds[-2]["inserted"] or (rounds[-1].get("held") or 0) > (rounds[-2].get("held") or 0):
        return None
    return (
        f"measuring {rounds[-2]['remeasured']} cell(s) again held no more points "
        f"({rounds[-1].get('held')} of {rounds[-1].get('points_judged')})"
    )


def reuse_where(
    previous_cells: list[dict[str, Any]], same: Callable[[Mapping[str, Any], bool], bool]
) -> Callable[[ValidationItem], list[dict[str, Any]] | None]:
    """run_validation's `reuse` for a refinement's next validation: where the drive injects the same theta as under
    the map validated before (`same(point, along_speed)`, service/maps/lut_export.py injection_unchanged: at a
    point, or at every speed of a run-up's torque), that validation's cells are taken as they are (reused, no plant
    time): a guard round changes a few cells, an insertion round the intervals it splits. A point or run-up pair
    not measured then, or measured then but not at its status `measured`, is measured."""
    earlier: dict[tuple[str, Cell], list[dict[str, Any]]] = {}
    for cell in previous_cells:
        earlier.setdefault((cell["kind"], _item_key(cell["kind"], cell["operating_point"])), []).append(cell)

    def reuse(item: ValidationItem) -> list[dict[str, Any]] | None:
        op = item.op.model_dump()
        cells = earlier.get((item.kind, _item_key(item.kind, op)))
        if item.not_run is not None or not cells or any(c["status"] != "measured" for c in cells):
            return None
        if not same(op, item.kind == "runup"):
            return None
        return [{**c, "plant_time_s": 0.0, "settle_plant_s": 0.0, "reused": True} for c in cells]

    return reuse


def _item_key(kind: str, op: Mapping[str, Any]) -> Cell:
    """A validation item's key: a point's operating point; a run-up pair's torque and U_dc (its bins' speeds vary)."""
    t, n, u = _cell_of(op)
    return (t, 0.0 if kind == "runup" else n, u)


def guard_cells(
    axes: dict[str, list[float]], map_cells: list[dict[str, Any]], harmful: list[dict[str, Any]]
) -> list[Cell]:
    """The cells to turn injection off at so that the drive gives no compensation, rather than a harmful one,
    where the LUT made things worse (LUT flag 3: every interval with such a cell as a corner injects nothing).
    Per harmful point: of the corners of the interval it lies in, the one with the smallest |theta| (the turn,
    where theta* passes near zero: turning it off costs least where the harm comes from)."""
    grid_values = {a: sorted(float(v) for v in axes[a]) for a in AXES}
    by_key = {_cell_of(c): c for c in map_cells}
    chosen: set[Cell] = set()
    for c in harmful:
        key = _cell_of(c["operating_point"])
        sides = [corner_values(grid_values[axis], key[i]) for i, axis in enumerate(AXES)]
        corners = [(t, n, u) for t in sides[0] for n in sides[1] for u in sides[2]]

        def gamma(corner: Cell) -> float:
            theta = _theta_at(by_key, corner)
            return math.inf if theta is None else math.hypot(*theta)

        chosen.add(min(corners, key=gamma))
    return sorted(chosen)
