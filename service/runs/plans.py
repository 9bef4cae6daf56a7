"""Sweep plans: what to do, separate from the engine that does it (bluesky's plans / run engine).

A plan is the ordered list of operating points of a grid; `dry_run` checks every setpoint
against the bench limits, and against the envelope model of the motor settings unless the request
overrides the model (service.model.limits), before the first frame goes out.

Plans that know the regime: above the field-weakening (FW) onset, which depends on torque and U_dc,
theta* turns by tens of degrees within a few hundred rpm, so a LUT whose speed axis straddles the
onset interpolates badly there. `plan_grid` predicts the onset of every (torque, U_dc) of a grid from
the NOMINAL settings (service.model.operating_point.field_weakening_onset) and, on request
(`RegimePlacement`), adds speed values at the onset and at onset +- spacing to the grid's speed axis,
so the map has cells on both sides of the turn. The planned grid is what a sweep stores and measures
(`Engine.submit_sweep`) and what `preview_sweep` (POST /sweeps/preview) shows; `SweepPlan.from_grid`
stays the one way its points are ordered.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, FiniteFloat, ValidationError, field_validator

from service.errors import Invalid
from service.identification.common import MethodOptions
from service.model.limits import (
    LimitError,
    check_any_inside,
    check_limits,
    outside_envelope,
    setpoint_problem,
)
from service.model.operating_point import OperatingPoint, field_weakening_onset
from service.runs.identify import PlantTimeError, check_plant_time, plant_time_bound_s
from service.settings import SafetySettings, Settings

MAX_GRID_POINTS = 10_000
MAX_SPEED_VALUES = 200  # the longest speed axis a grid may have (speeds placed by a plan included)


def settling_order(points: list[OperatingPoint]) -> list[OperatingPoint]:
    """`points` in the order a continuous run settles them fastest: U_dc outermost, then torque, speed innermost
    with its direction alternating from one torque to the next, so consecutive points differ by one speed step. A
    torque step is what costs a point its settling (the load's speed loop rejects it and the shaft rings), a step of
    the load's speed ramp far less: measured on paper-bench (service/bench/measurement.py settle_operating_point,
    plant time from the move's effect to steady), a 4 x 13 map's validation at 12.5 rpm steps settles a point in
    0.43 s with torque innermost and 0.11 s with speed innermost; a 4 x 5 map's, at 200 rpm steps, 0.32 and 0.13 s."""
    rows: dict[tuple[float, float], list[OperatingPoint]] = {}
    for op in points:
        rows.setdefault((op.udc_v, op.torque_nm), []).append(op)
    ordered: list[OperatingPoint] = []
    for k, key in enumerate(sorted(rows)):
        ordered += sorted(rows[key], key=lambda op: op.speed_rpm, reverse=k % 2 == 1)
    return ordered


class Grid(BaseModel):
    """Operating-point grid: torque x speed x DC-link voltage."""

    model_config = ConfigDict(extra="forbid")
    torque_nm: list[FiniteFloat] = Field(..., min_length=1, max_length=200, description="torque commands T* in Nm")
    speed_rpm: list[FiniteFloat] = Field(
        ..., min_length=1, max_length=MAX_SPEED_VALUES, description="mechanical speeds in rpm"
    )
    udc_v: list[FiniteFloat] = Field(
        default_factory=lambda: [12.0], min_length=1, max_length=50, description="DC-link voltages in V"
    )

    @field_validator("torque_nm", "speed_rpm", "udc_v")
    @classmethod
    def _sorted_unique(cls, values: list[float]) -> list[float]:
        if len(set(values)) != len(values):
            raise ValueError("values must be unique")
        return sorted(values)

    def size(self) -> int:
        return len(self.torque_nm) * len(self.speed_rpm) * len(self.udc_v)


class SweepTooLarge(Invalid, ValueError):
    """A grid above `safety.max_sweep_points_unconfirmed` sent without `confirm_large`."""

    at = "confirm_large"
    error_type = "value_error.confirm_large"


def check_sweep_size(grid: Grid, confirm_large: bool, safety: SafetySettings) -> None:
    """A sweep that runs for hours is started on purpose: above the configured size it needs the flag."""
    if grid.size() > MAX_GRID_POINTS:
        raise ValueError(f"grid has {grid.size()} points, more than the maximum of {MAX_GRID_POINTS}")
    if grid.size() > safety.max_sweep_points_unconfirmed and not confirm_large:
        raise SweepTooLarge(
            f"grid has {grid.size()} points, more than {safety.max_sweep_points_unconfirmed} "
            f"(safety.max_sweep_points_unconfirmed): send \"confirm_large\": true to run it"
        )


@dataclass(frozen=True)
class SweepPlan:
    points: tuple[OperatingPoint, ...]

    @classmethod
    def from_grid(cls, grid: Grid) -> "SweepPlan":
        """The grid's points in settling_order: U_dc outermost (the supply is slowest to change), then torque, speed
        innermost in alternating direction (measured, a 10 x 10 probe sweep over 0.5..5 Nm x 500..3200 rpm on
        paper-bench, tests/benchmarks/bench_sweep_quality.py: 41.9 s of bench time, 11.0 s of it settling, against
        53.3 s and 23.4 s with torque innermost before; the same 77 cells ok)."""
        if grid.size() > MAX_GRID_POINTS:
            raise ValueError(f"grid has {grid.size()} points, more than {MAX_GRID_POINTS}")
        points = [
            OperatingPoint(torque_nm=t, speed_rpm=n, udc_v=u)
            for u in grid.udc_v
            for n in grid.speed_rpm
            for t in grid.torque_nm
        ]
        return cls(tuple(settling_order(points)))

    def dry_run(self, settings: Settings, override_envelope_model: bool = False) -> None:
        """Raise LimitError naming every point that violates the bench limits (never overridden), then
        EnvelopeError if no point is inside the envelope model (unless `override_envelope_model`); the points
        outside it are not run (service.model.limits.outside_envelope: the sweep stores them failed with the
        reason, as a full-load curve clips a bench's grid). Sends nothing."""
        self.check_limits(settings)
        check_any_inside(list(self.points), settings, override_envelope_model)

    def check_limits(self, settings: Settings) -> None:
        """LimitError naming every point outside the bench limits (never overridden)."""
        problems: list[str] = []
        fields: dict[str, list[str]] = {}
        for op in self.points:
            try:
                check_limits(op, settings)
            except LimitError as exc:
                problems.append(_named(op, str(exc)))
                for field, msg in exc.problems:
                    fields.setdefault(field, []).append(_named(op, msg))
        if problems:
            # one entry per grid field, the first few points named (a 400-point grid would flood the answer)
            per_field = tuple((f, f"{len(m)} point(s): " + " | ".join(m[:5])) for f, m in fields.items())
            raise LimitError(
                f"{len(problems)} point(s) outside the bench limits: " + " | ".join(problems[:10]), per_field
            )


def check_grid_limits(grid: Grid, settings: Settings) -> None:
    """LimitError naming, per axis (its field in the grid), every value outside the bench's hard limits, in the words
    and with the limits of this bench (service/model/limits.py setpoint_problem), before a point is made of them."""
    problems = []
    for field in ("torque_nm", "speed_rpm", "udc_v"):
        found = [p for v in getattr(grid, field) if (p := _grid_value_problem(field, v, settings)) is not None]
        if found:
            more = f" (and {len(found) - 5} more)" if len(found) > 5 else ""
            problems.append((field, " | ".join(found[:5]) + more))
    if problems:
        raise LimitError("; ".join(msg for _, msg in problems), tuple(problems))


class OrdersError(Invalid, ValueError):
    """A request's `orders` without this bench's harmonic order (each point cancels it, the others with it)."""

    at = "orders"


def check_orders(orders: list[int] | None, harmonic_order: int) -> None:
    """OrdersError unless `orders` (a request's, None: the harmonic order alone) includes `harmonic_order`."""
    if orders is not None and harmonic_order not in orders:
        raise OrdersError(
            f"orders {orders} do not include this bench's harmonic order {harmonic_order} "
            "(identification.harmonic_order): each point cancels it, the others with it"
        )


def _grid_value_problem(field: str, value: float, settings: Settings) -> str | None:
    """setpoint_problem, and a grid speed is a magnitude (the limits take |speed|: a setpoint may turn either way;
    an operating point's speed is > 0): a speed <= 0 is named with the bench's minimum as any speed below it."""
    if field == "speed_rpm" and value <= 0:
        return (
            f"speed_rpm {value:g} is below the minimum of {settings.safety.min_speed_rpm:g} rpm (safety.min_speed_rpm): "
            "a grid's speeds are magnitudes, > 0"
        )
    return setpoint_problem(field, value, settings.safety)


def _named(op: OperatingPoint, msg: str) -> str:
    """`msg` beginning with the point it is about (the envelope's messages name it already)."""
    return msg if msg.startswith(op.label()) else f"{op.label()}: {msg}"


# --- plans that know the regime ---------------------------------------------------------------------
class RegimePlacement(BaseModel):
    """Speed values placed around the predicted field-weakening onset of each torque (see plan_grid)."""

    model_config = ConfigDict(
        extra="forbid",
        allow_inf_nan=False,
        json_schema_extra={"examples": [{"speeds_around_onset": True, "spacing_rpm": 100}]},
    )
    speeds_around_onset: bool = Field(
        False,
        description="add to the speed axis, within the grid's speed range, the "
        "predicted field-weakening onset of every torque and U_dc (rounded to round_rpm) "
        "and onset +- spacing_rpm, so the map has cells on both sides of the turn of theta*",
    )
    spacing_rpm: float = Field(
        100.0, ge=10.0, le=2000.0, description="distance of the speed values placed below and above each onset, rpm"
    )
    round_rpm: float = Field(10.0, ge=1.0, le=500.0, description="the onset is rounded to a multiple of this, rpm")


class OnsetPrediction(BaseModel):
    """The predicted field-weakening onset of one torque at one U_dc (nominal settings)."""

    torque_nm: float = Field(..., description="torque command T* of the grid, Nm")
    udc_v: float = Field(..., description="DC-link voltage of the grid, V")
    onset_rpm: float | None = Field(
        ...,
        description="mechanical speed at which |u_dq| with i_d = 0 reaches "
        "control.voltage_margin * U_dc / sqrt(3), rpm (rounded to 0.1); null: no onset up "
        "to safety.max_speed_rpm (see note)",
    )
    placed_rpm: float | None = Field(
        None,
        description="the onset rounded to regime.round_rpm, where speeds were "
        "placed around it (null: none placed for this torque)",
    )
    in_speed_range: bool = Field(..., description="the onset lies within the grid's speed range (min..max)")
    note: str | None = Field(None, description="why there is no onset, or why nothing was placed around it")


class SpeedValue(BaseModel):
    """One value of the planned speed axis."""

    speed_rpm: float = Field(..., description="mechanical speed, rpm")
    added: bool = Field(..., description="placed by the plan (not in the requested grid)")
    reasons: list[str] = Field(
        default_factory=list, description="why the plan placed it (also for a value the requested grid already had)"
    )


class RegimeError(Invalid, ValueError):
    """Placing speeds around the onset gives a grid that cannot be measured (too many speed values)."""

    at = "regime"


@dataclass(frozen=True)
class PlannedGrid:
    requested: Grid  # the grid as asked for
    grid: Grid  # the grid the sweep stores and measures
    onsets: tuple[OnsetPrediction, ...]  # per U_dc, then torque (the grid's order)
    speed_axis: tuple[SpeedValue, ...]  # the planned speed axis, sorted

    @property
    def added_speeds_rpm(self) -> list[float]:
        return [v.speed_rpm for v in self.speed_axis if v.added]


def _multiple(value: float, step: float) -> float:
    """`value` rounded to the nearest multiple of `step` (halves up, not to even: 1965 -> 1970 at 10)."""
    return round(math.floor(value / step + 0.5) * step, 6)


def plan_grid(grid: Grid, regime: RegimePlacement | None, settings: Settings) -> PlannedGrid:
    """The grid a sweep measures: `grid`, plus (if `regime.speeds_around_onset`) for every torque and U_dc
    whose predicted field-weakening onset lies within the grid's speed range, the speed values at the
    onset (rounded to regime.round_rpm) and at onset -+ regime.spacing_rpm that lie within that range,
    merged into the speed axis (sorted, unique). The onset is predicted from the NOMINAL motor settings
    and control.voltage_margin (field_weakening_onset, eq. 18-20); onsets above safety.max_speed_rpm
    count as none. Raises RegimeError when the merged axis would exceed MAX_SPEED_VALUES."""
    motor, margin = settings.motor, settings.control.voltage_margin
    lo, hi = grid.speed_rpm[0], grid.speed_rpm[-1]
    placement = regime if regime is not None and regime.speeds_around_onset else None
    reasons: dict[float, list[str]] = {}
    onsets = []
    for udc in grid.udc_v:
        for torque in grid.torque_nm:
            onset = field_weakening_onset(torque, udc, motor, margin)
            speed, note = onset.speed_rpm, onset.reason
            if speed is not None and speed > settings.safety.max_speed_rpm:
                speed, note = (
                    None,
                    (
                        f"onset at {onset.speed_rpm:.0f} rpm, above safety.max_speed_rpm "
                        f"({settings.safety.max_speed_rpm:g} rpm): no field weakening within the bench's speeds"
                    ),
                )
            in_range = speed is not None and lo <= speed <= hi
            placed = None
            if speed is not None and not in_range:
                note = f"outside the grid's speeds ({lo:g}..{hi:g} rpm): the map does not cross it"
            elif speed is not None and in_range and placement is not None:
                placed = _multiple(speed, placement.round_rpm)
                where = f"the field-weakening onset of {torque:g} Nm at {udc:g} V (predicted {speed:.0f} rpm)"
                spacing_rpm = placement.spacing_rpm
                for value, why in (
                    (placed - spacing_rpm, f"{spacing_rpm:g} rpm below {where}"),
                    (placed, where),
                    (placed + spacing_rpm, f"{spacing_rpm:g} rpm above {where}"),
                ):
                    value = round(value, 6)
                    if lo <= value <= hi:
                        reasons.setdefault(value, []).append(why)
            onsets.append(
                OnsetPrediction(
                    torque_nm=torque,
                    udc_v=udc,
                    onset_rpm=None if speed is None else round(speed, 1),
                    placed_rpm=placed,
                    in_speed_range=in_range,
                    note=note,
                )
            )
    requested = set(grid.speed_rpm)
    axis = sorted(requested | set(reasons))
    try:
        planned = (
            grid if len(axis) == len(requested) else Grid(torque_nm=grid.torque_nm, speed_rpm=axis, udc_v=grid.udc_v)
        )
    except ValidationError:
        raise RegimeError(
            f"placing speeds around the onset gives {len(axis)} speed values, more than the grid's "
            f"{MAX_SPEED_VALUES}: fewer torques or U_dc values, or a narrower speed range"
        ) from None
    speed_axis = tuple(SpeedValue(speed_rpm=v, added=v not in requested, reasons=reasons.get(v, [])) for v in axis)
    return PlannedGrid(grid, planned, tuple(onsets), speed_axis)


# --- the preview: the plan without queueing anything ---------------------------------------------------
# Bench time is an ESTIMATE at speedup 1 (real time: a real bench, or the emulator paced to it; the
# emulator at --speedup 0 runs faster). Per point: the move and the settling by measurement, plus the
# method's measurement. The typical measurement figures are the mean-ish plant time per point of the
# 10 x 10 paper-bench sweeps (README, Performance: median 0.15-0.31 s, p95 1.3-1.7 s); a method
# without a figure (e.g. grid, which always walks its whole grid) counts its options' worst case.
ESTIMATE_SETTLE_S_PER_POINT = 0.5  # torque step / speed ramp, CAN round trips, settling by measurement
ESTIMATE_MEASUREMENT_S = {"adaptive": 0.4, "probe": 0.3}
ESTIMATE_UDC_CHANGE_S = 2.0  # the supply set over SCPI and confirmed, torque off meanwhile
ESTIMATE_RUN_START_S = 3.0  # drive enabled, load spun up, setpoint accounting established


class BenchTimeEstimate(BaseModel):
    """An ESTIMATE of the bench time the sweep takes, wall seconds at speedup 1 (real time)."""

    estimated_s: float | None = Field(
        ..., description="run start + per U_dc change + per point (settle_s_per_point + measurement_s_per_point)"
    )
    worst_case_s: float | None = Field(
        ...,
        description="the same with every point at its method options' worst-case "
        "plant time (the bound refused above safety.max_plant_s_per_point)",
    )
    settle_s_per_point: float = Field(..., description="assumed move and settling per point, s")
    measurement_s_per_point: float | None = Field(
        ...,
        description="assumed typical measurement per point, s (the method's "
        "typical plant time, or its worst case where no typical figure is known)",
    )
    udc_changes: int = Field(..., description="changes of the DC-link voltage (the supply is set and confirmed)")
    basis: str = Field(..., description="how the estimate is made")


class SweepPreview(BaseModel):
    """The plan of a sweep request as POST /sweeps would queue it, without queueing anything."""

    accepted: bool = Field(..., description="POST /sweeps with this body would queue it (a token aside)")
    problems: list[dict[str, Any]] = Field(
        ...,
        description="what POST /sweeps would refuse, as the items of its 422 "
        "detail ({loc, msg, type}); unlike POST /sweeps, which stops at the first "
        "kind (size, plant time, bench limits, envelope model: type value_error.envelope), every kind is listed",
    )
    total: int = Field(..., description="number of operating points")
    requested_grid: Grid = Field(..., description="the grid as requested")
    grid: Grid = Field(..., description="the planned grid: what the sweep stores and measures (its map's axes)")
    points: list[OperatingPoint] = Field(
        ...,
        description="the operating points in the order they will be measured "
        "(U_dc outermost, then torque, speed innermost, alternating direction); empty "
        "when the grid cannot be planned",
    )
    speed_axis: list[SpeedValue] = Field(
        ..., description="the planned speed axis with the values the plan added and why"
    )
    added_speeds_rpm: list[float] = Field(..., description="the speed values the plan added, rpm")
    onsets: list[OnsetPrediction] = Field(..., description="the predicted field-weakening onset per (torque, U_dc)")
    voltage_margin: float = Field(..., description="control.voltage_margin the onsets were predicted with")
    estimate: BenchTimeEstimate | None = Field(
        ..., description="bench time, an estimate (null when the grid cannot be planned)"
    )
    not_run: list[dict[str, Any]] = Field(
        default_factory=list,
        description="the points the envelope model of the motor settings refuses ({operating_point, reason}): the "
        "sweep stores each failed with its reason and never moves the bench there (override_envelope_model runs "
        "them, the actuals interlock still holding the hard limits)",
    )


def _problem(loc: list[str], msg: str, type_: str = "value_error") -> dict[str, Any]:
    return {"loc": loc, "msg": msg, "type": type_}


def _limit_problems(exc: LimitError) -> list[dict[str, Any]]:
    """A refusal of the grid as 422 items: one per grid field it names, else one for the grid."""
    return [_problem(["body", "grid", field], msg, exc.kind) for field, msg in exc.problems] or [
        _problem(["body", "grid"], str(exc), exc.kind)
    ]


def _estimate(
    points: tuple[OperatingPoint, ...], method: str, options: MethodOptions, settings: Settings
) -> BenchTimeEstimate:
    h, pole_pairs = settings.identification.harmonic_order, settings.motor.pole_pairs

    def bound_s(op: OperatingPoint) -> float:
        try:
            return float(plant_time_bound_s(options, op.speed_rpm / 60.0 * pole_pairs * h))
        except (ArithmeticError, ValueError):
            return math.inf

    bounds = [bound_s(op) for op in points]
    udc_changes = sum(1 for a, b in zip(points, points[1:]) if a.udc_v != b.udc_v)
    fixed_s = ESTIMATE_RUN_START_S + udc_changes * ESTIMATE_UDC_CHANGE_S + len(points) * ESTIMATE_SETTLE_S_PER_POINT
    worst_s = fixed_s + sum(bounds)
    typical = ESTIMATE_MEASUREMENT_S.get(method)
    if typical is None:
        estimated_s = worst_s
        typical = sum(bounds) / len(bounds) if bounds else 0.0
        basis = f"the {method} method's worst case per point (its options' plant-time bound)"
    else:
        estimated_s = fixed_s + len(points) * typical
        basis = f"{typical:g} s typical {method} plant time per point (paper-bench sweeps)"
    return BenchTimeEstimate(
        estimated_s=round(estimated_s, 1) if math.isfinite(estimated_s) else None,
        worst_case_s=round(worst_s, 1) if math.isfinite(worst_s) else None,
        settle_s_per_point=ESTIMATE_SETTLE_S_PER_POINT,
        measurement_s_per_point=round(typical, 3) if math.isfinite(typical) else None,
        udc_changes=udc_changes,
        basis=(
            f"estimate at speedup 1 (real time): {ESTIMATE_RUN_START_S:g} s run start, {ESTIMATE_UDC_CHANGE_S:g} s "
            f"per U_dc change, per point {ESTIMATE_SETTLE_S_PER_POINT:g} s move and settling + {basis}; "
            "the emulator at speedup 0 is faster"
        ),
    )


def preview_sweep(
    grid: Grid,
    regime: RegimePlacement | None,
    method: str,
    options: MethodOptions,
    confirm_large: bool,
    settings: Settings,
    orders: list[int] | None = None,
) -> SweepPreview:
    """The plan POST /sweeps would queue for this request (plan_grid, then SweepPlan.from_grid, the same
    steps Engine.submit_sweep takes) and every check it would make, answered as a list: the grid's size
    (confirm_large), the options' plant time, the dry run against the bench limits and (unless the options
    override it) the envelope model of the motor settings. Moves nothing."""
    problems: list[dict[str, Any]] = []
    try:
        check_orders(orders, settings.identification.harmonic_order)
    except OrdersError as exc:
        problems.append(_problem(["body", "orders"], str(exc)))
    try:
        planned = plan_grid(grid, regime, settings)
    except RegimeError as exc:
        problems.append(_problem(["body", "regime"], str(exc)))
        planned = plan_grid(grid, None, settings)  # the onsets are still worth showing
    try:
        check_sweep_size(planned.grid, confirm_large, settings.safety)
    except SweepTooLarge as exc:
        problems.append(_problem(["body", "confirm_large"], str(exc), "value_error.confirm_large"))
    except ValueError as exc:
        problems.append(_problem(["body", "grid"], str(exc)))
    points: tuple[OperatingPoint, ...] = ()
    override = options.override_envelope_model
    try:  # each grid value against the bench's limits, as POST /sweeps checks them first
        check_grid_limits(planned.grid, settings)
        within_limits = True
    except LimitError as exc:
        problems += _limit_problems(exc)
        within_limits = False
    # points only of values within the limits (a speed <= 0 makes no operating point; named above)
    if planned.grid.size() <= MAX_GRID_POINTS and within_limits:
        points = SweepPlan.from_grid(planned.grid).points
    # the envelope model (unless the request overrides it) judges each point once: the points outside it are
    # listed apart (not run), the rest are what the sweep runs
    inside: list[OperatingPoint] = []
    not_run: list[tuple[OperatingPoint, str]] = []
    for op in points:
        why = outside_envelope(op, settings, override)
        if why is None:
            inside.append(op)
        else:
            not_run.append((op, why))
    if points:
        try:
            check_plant_time(planned.grid.speed_rpm, method, options, settings)
        except PlantTimeError as exc:
            problems.append(_problem(["body", "options"], str(exc), "value_error.plant_time"))
        # the envelope model: refused only when no point is inside it (check_any_inside words that refusal,
        # judging the points again, only then)
        if not inside:
            try:
                check_any_inside(list(points), settings, override)
            except LimitError as exc:
                problems += _limit_problems(exc)
    runs = tuple(inside) or points
    return SweepPreview(
        accepted=not problems,
        problems=problems,
        total=planned.grid.size(),
        requested_grid=grid,
        grid=planned.grid,
        points=list(points),
        speed_axis=list(planned.speed_axis),
        added_speeds_rpm=planned.added_speeds_rpm,
        onsets=list(planned.onsets),
        voltage_margin=settings.control.voltage_margin,
        estimate=_estimate(runs, method, options, settings) if runs else None,
        not_run=[{"operating_point": op.model_dump(), "reason": why} for op, why in not_run],
    )
