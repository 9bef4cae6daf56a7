"""A map proven in the drive's own LUT mode (issue 11): download its LUT, switch the drive to LUT
mode (0x2000:2 = 2) and measure, at every grid point and at the midpoints between neighbouring grid
points, how much of the h-th harmonic the drive's own feedforward leaves.

Points: per axis of length n > 1 the finer axis with 2n-1 values (the grid values and the midpoint
between each neighbouring pair); a single-valued axis stays as it is. Every point of the finer grid
is measured; `kind` is `grid` where all its coordinates are grid values, else `midpoint` (the drive
interpolates theta multilinearly there: untrained points).

At each point (bench.operating_point: move, settle on the DAQ clock, always leave safe):
  1. injection mode off, the uncompensated phasor A_0 (identification.common.measure_reference,
     known to 1 % of itself);
  2. injection mode LUT (no theta from the service), the residual phasor A_lut, its window extended
     until the noise floor sqrt(2) sigma sits `floor_db` below |A_0| (or max_window_s is reached);
  3. suppression_db = 20 log10(|A_0| / |A_lut|) (the same figure as an identification's,
     service.identification.common), with noise_floor_db = 20 log10(sqrt(2) sigma / |A_0|) of the
     LUT window. A residual within 3 sqrt(2) sigma of zero is `at_noise_floor`: the figure is then
     a lower bound, not the LUT's true suppression.
A point that faulted or could not be measured carries its reason and no number. An interlock trip
or a cancel stops the run (the points not reached say so); the bench is made safe after every
point and after the run (torque 0, injection mode off, drive disabled).
"""

from __future__ import annotations

import math
import statistics
import threading
import time
from dataclasses import dataclass, field
from itertools import product
from typing import Any, Callable, cast

from pydantic import BaseModel, ConfigDict, Field

from service import __version__
from service.bench.bench import Bench
from service.bench.measurement import RunCancelled
from service.bench.run import BenchRun
from service.bench.trips import InterlockTripped
from service.errors import BenchRefused, Invalid
from service.identification.common import (
    MIN_PERIODS,
    floor_amplitude,
    measure_reference,
    noise_floor_db,
    periods_for,
)
from service.identification.session import MeasurementError, MeasurementSession, Window
from service.maps.lut_export import Interpolation, injects_nothing
from service.maps.view import MapView, map_view
from service.model.harmonic import Phasor
from service.model.limits import check_any_inside, check_limits, outside_envelope, torque_departure
from service.model.operating_point import OperatingPoint
from service.runs import lut_download
from service.runs.plans import settling_order
from service.runs.runup_validation import mark_no_injection, measure_runup_pair, runup_range, runup_torques
from service.settings import Settings
from service.store.storage import Storage, now_iso

# a running validation spends at most ~1/40 of its wall time storing its progress (a refined map's 0.2 s stores then
# come every ~8 s; at 1/10 they cost a calibration's validation 17 s of its 226 s at speedup 0, and its tenth at a
# real bench's clock); its cells are told as they are measured (on_cell: the live view) all the same
STORE_SPACING = 40.0


class ValidationOptions(BaseModel):
    """How finely each point is measured. Every field bounded."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    floor_db: float = Field(
        55.0,
        ge=20,
        le=80,
        description="the LUT window is extended until its noise floor is this "
        "far below the uncompensated amplitude, dB",
    )
    max_window_s: float = Field(0.4, gt=0, le=5.0, description="longest window at one point, plant s")
    settle_s: float = Field(
        0.02, ge=0, le=2.0, description="plant time after the injection mode switch before measuring, s"
    )
    fill: bool = Field(
        True,
        description="the map's fills go into the drive too (the validation measures what the "
        "drive does at filled cells)",
    )
    interpolation: Interpolation | None = Field(
        None, description="what the drive interpolates between cells (default: the service's)"
    )
    override_envelope_model: bool = Field(
        False,
        description="validate at points the envelope model of the motor settings refuses (a machine known "
        "to exceed its nominal settings); never the hard limits, held on the actuals by the interlock",
    )
    target_db: float = Field(
        30.0, ge=0, le=80, description="a judged point holds at this suppression (or below the floor rule), dB"
    )
    runups: bool = Field(
        False,
        description="also judge the LUT along run-ups: at every torque row and midpoint between rows, a run-up "
        "without and one with the LUT over the map's speed range, every speed bin a judged point "
        "(service/runs/runup_validation.py)",
    )
    runup_rate_rpm_per_s: float = Field(100.0, ge=10, le=1000, description="the run-ups' ramp rate, rpm/s")
    runup_torques_max: int | None = Field(
        None,
        ge=2,
        le=200,
        description="run up at most this many torques, evenly spread over the rows and midpoints (both ends "
        "included); None: at every row and midpoint. A refined map has many rows: bench time is the budget",
    )


class ValidationRefused(Invalid, ValueError):
    """The map cannot be validated as asked (no valid cell; a partial map without force)."""


class ValidationStopped(BenchRefused, RuntimeError):
    """An interlock trip stopped the validation (the cells measured before it are stored)."""


def finer_axis(values: list[float]) -> list[tuple[float, bool]]:
    """(value, is_grid_value) along an axis: the grid values and their neighbours' midpoints."""
    out = []
    for a, b in zip(values, values[1:]):
        out += [(float(a), True), ((float(a) + float(b)) / 2.0, False)]
    return out + [(float(values[-1]), True)]


def validation_points(axes: dict[str, list[float]]) -> list[tuple[OperatingPoint, str]]:
    """Every point of the finer grid, in the order measured (service.runs.plans.settling_order: speed innermost),
    with its kind: grid | midpoint."""
    kinds = {
        OperatingPoint(torque_nm=t, speed_rpm=n, udc_v=u): "grid" if ug and ng and tg else "midpoint"
        for (u, ug), (n, ng), (t, tg) in product(
            finer_axis(axes["udc_v"]), finer_axis(axes["speed_rpm"]), finer_axis(axes["torque_nm"])
        )
    }
    return [(op, kinds[op]) for op in settling_order(list(kinds))]


def check_validatable(storage: Storage, map_id: int, force: bool, fill: bool = True) -> None:
    """The download rules (service/runs/lut_download.py: no ok cell is refused, a partial map needs
    `force`) checked before anything is queued."""
    try:
        lut_download.prepare(storage, map_id, force, fill=fill)
    except lut_download.PartialMap as exc:
        raise ValidationRefused(f'{exc.what}; validate it anyway with "force": true in the request') from None
    except lut_download.LutRefused as exc:
        raise ValidationRefused(str(exc)) from None


def download_into_drive(
    storage: Storage, bench: Bench, map_id: int, force: bool, fill: bool = True, interpolation: str | None = None
) -> dict[str, Any]:
    """The map's LUT into the drive, CRC-32 and map id read back (service.runs.lut_download.download_map,
    the one way a map goes into the drive): the receipt."""
    return lut_download.download_map(storage, bench, map_id, force, fill=fill, interpolation=interpolation).model_dump()


@dataclass
class ValidationRun:
    """What a validation job found so far (stored from the download on, after every point, and as it
    ends, whatever ends it: store_validation)."""

    map_id: int
    harmonic_order: int
    options: dict[str, Any]
    cells: list[dict[str, Any]] = field(default_factory=list)
    download: dict[str, Any] | None = None
    state: str = "done"  # done | failed | cancelled (running while stored before its end)
    error: str | None = None
    started_at: str = field(default_factory=now_iso)
    row_id: int | None = None  # its map_validations row, once stored
    runup_plant_time_s: float = 0.0  # the run-up pairs' (their bins carry none each)
    runups_reused: int = 0  # uncompensated run-ups taken from an earlier validation of the same bench and ramp
    items_reused: int = 0  # points and run-up pairs taken from an earlier validation where the LUT is the same

    def summary(self) -> dict[str, Any]:
        out = summarize(self.cells, self.harmonic_order)
        out["plant_time_s"] += self.runup_plant_time_s
        out["runup_plant_time_s"] = self.runup_plant_time_s
        out["runups_reused"] = self.runups_reused
        out["items_reused"] = self.items_reused
        return out


def measured_decoupling(storage: Storage, m: MapView, settings: Settings) -> bool:
    """The drive decoupling (0x2000:6) the map's ok cells were measured with: the LUT holds only with
    it. Cells stored before results recorded it count as the settings' default. A map mixing both
    cannot be validated as one LUT."""
    used = set()
    for row in storage.results_by_id([c.result_id for c in m.cells if c.status == "ok" and c.result_id]).values():
        details = (row.get("detail") or {}).get("details") or {}
        used.add(bool(details.get("decoupling", settings.identification.decoupling)))
    if len(used) > 1:
        raise ValueError(
            f"map {m.id} mixes cells measured with and without drive decoupling: validate maps measured one way"
        )
    return used.pop() if used else settings.identification.decoupling


def measure_point(
    run: BenchRun, op: OperatingPoint, options: ValidationOptions, further_orders: tuple[int, ...] = ()
) -> dict[str, Any]:
    """One point of a validation run (service.bench.run.BenchRun): uncompensated (injection off),
    then the drive's own LUT feedforward (module doc). `further_orders`: a map of several orders' other orders,
    each judged from the same two windows (whole electrical turns: every order is whole in them) in `orders`."""
    with run.operating_point(op) as session:
        session.settle_after_theta_s = options.settle_s
        session.also_orders = further_orders  # the map's own order fitted with its other orders beside
        # the bench's session is a MeasurementSession; the protocol declares harmonic_frequency_hz a settable
        # attribute where the session has a read-only property (service/identification/session.py)
        measurement = cast(MeasurementSession, session)
        max_periods = periods_for(measurement, options.max_window_s)  # >= MIN_PERIODS
        session.apply_injection_mode("off")
        reference = measure_reference(measurement, MIN_PERIODS, max_periods)
        a0 = reference.phasor.amplitude
        session.apply_injection_mode("lut")
        # noise floor sqrt(2) sigma at floor_db below |A_0|
        sigma_fs = a0 * 10.0 ** (-options.floor_db / 20.0) / math.sqrt(2.0)
        residual = session.measure(MIN_PERIODS, max_noise_std_fs=sigma_fs, max_periods=max_periods)
        plant_time_s = session.plant_time_s
        settle_plant_s = session.op_settle_plant_s
        speed_rpm = session.speed_rpm_measured
        f_h = session.harmonic_frequency_hz
        torque_actual_nm, _ = run.torque_actual()  # the torque the point ran at, over its measurement
        every_order = (session.harmonic_order, *further_orders)  # each fitted beside the others
        orders = [
            _order_figures(
                h,
                measurement.order_window(reference, h, every_order).phasor,
                measurement.order_window(residual, h, every_order),
                options,
            )
            for h in further_orders
        ]
    departure = torque_departure(op.torque_nm, torque_actual_nm, run.bench.settings.safety)
    if departure is not None:
        raise MeasurementError(departure)  # a figure at a torque the motor did not run at is no figure of the map
    a = residual.phasor.amplitude
    if a0 <= 0 or a <= 0:
        raise ValueError(f"a phasor of zero amplitude (uncompensated {a0:g}, LUT {a:g} fs): nothing to compare")
    suppression_db = 20.0 * math.log10(a0 / a)
    floor_db = noise_floor_db(residual, a0)
    return {
        "suppression_db": suppression_db,
        "above_floor_db": -floor_db if floor_db is not None else None,
        "holds": suppression_db >= options.target_db,
        "uncompensated": reference.phasor.as_dict(),
        "residual": residual.phasor.as_dict(),
        "noise_floor_db": floor_db,
        "at_noise_floor": a <= floor_amplitude(residual.noise_std_fs),
        "plant_time_s": plant_time_s,
        "settle_plant_s": settle_plant_s,
        "speed_rpm_measured": speed_rpm,
        "harmonic_frequency_hz": f_h,
        "torque_actual_nm": torque_actual_nm,
        "bench_time_s": run.timing.public(),
        **({"orders": orders} if orders else {}),
    }


def _order_figures(order: int, uncompensated: Phasor, window: Window, options: ValidationOptions) -> dict[str, Any]:
    """A further order's figure at a validation point: its suppression from its own uncompensated phasor and the
    LUT-mode window of that order (its phasor and its own noise), judged against the validation's target as the
    map's own order is."""
    residual = window.phasor
    a0, a = uncompensated.amplitude, residual.amplitude
    suppression_db = 20.0 * math.log10(a0 / a) if a0 > 0 and a > 0 else None
    floor_db = noise_floor_db(window, a0)
    return {
        "order": order,
        "suppression_db": suppression_db,
        "above_floor_db": -floor_db if floor_db is not None else None,
        "holds": suppression_db is not None and suppression_db >= options.target_db,
        "uncompensated": uncompensated.as_dict(),
        "residual": residual.as_dict(),
        "at_noise_floor": a <= floor_amplitude(window.noise_std_fs),
    }


def run_validation(
    storage: Storage,
    bench: Bench,
    settings: Settings,
    map_id: int,
    force: bool,
    options: ValidationOptions,
    cancel: threading.Event,
    on_cell: Callable[[dict[str, Any], int], None] | None = None,
    download: Callable[..., dict[str, Any]] = download_into_drive,
    on_progress: Callable[[ValidationRun], object] | None = None,
    uncompensated: dict[tuple[float, ...], dict[str, Any]] | None = None,
    reuse: Callable[[ValidationItem], list[dict[str, Any]] | None] | None = None,
) -> ValidationRun:
    """The whole job: download, then every point in one continuous bench run (service/bench/run.py:
    the drive enabled and the load turning from point to point; a run that the bench itself broke
    is made safe and a new one goes on from the next point). Never raises for a point: a failed point
    is a cell with its reason; an interlock trip or a cancel ends the run with state failed /
    cancelled and the remaining cells marked not measured. Errors before the first point (download)
    do raise. `on_progress(run)` is told after the download and then as points finish, spaced by STORE_SPACING
    times what it took (the job stores it; the caller stores the end).
    `uncompensated`: run-ups without injection kept across validations of one bench (runup_validation.py
    measure_runup_pair). `reuse(item)`: an earlier validation's cells for an item where the drive's LUT is the
    same as then (a refinement's guard round changes a few cells), taken as they are; None: measured."""
    m = map_view(storage, map_id)
    if m is None:
        raise KeyError(f"map {map_id} does not exist")
    h = m.harmonic_order
    run = ValidationRun(map_id=map_id, harmonic_order=h, options=options.model_dump())
    decoupling = measured_decoupling(storage, m, settings)
    run.options["decoupling"] = decoupling
    run.download = download(storage, bench, map_id, force, fill=options.fill, interpolation=options.interpolation)
    if on_progress is not None:
        on_progress(run)  # stored now: the drive holds this LUT from here on
    items = validation_items(m.axes, settings, options)
    # where the drive injects nothing (the guard's cells off), a figure is no compensation, never harm
    nothing = injects_nothing(m.model_dump(), options.fill, options.interpolation)
    # a grid point whose cell is not ok carries no injection in the LUT: say so beside its figure
    map_cells = {(c.torque_nm, c.speed_rpm, c.udc_v): c for c in m.cells}

    def new_cell(op: OperatingPoint, kind: str) -> dict[str, Any]:
        cell: dict[str, Any] = {"operating_point": op.model_dump(), "kind": kind}
        if kind == "grid":
            c = map_cells.get((op.torque_nm, op.speed_rpm, op.udc_v))
            cell["map_cell_status"] = c.status if c is not None else "missing"
            cell["map_cell_filled"] = bool(c is not None and c.filled and options.fill)
        return cell

    stored_at, store_s = time.monotonic(), 0.0

    def finish(*cells: dict[str, Any]) -> None:
        nonlocal stored_at, store_s
        run.cells.extend(cells)
        # stored as it measures, but spaced by STORE_SPACING times what a store took (a store writes every cell
        # so far: a small map's after each point, a refined map's thousands, 0.1-0.2 s each, every few seconds;
        # stored per item, a row of points outside the envelope held the run's loop past the bench watchdog's
        # 3 s); the caller stores the end
        if on_progress is not None and time.monotonic() - stored_at >= STORE_SPACING * store_s:
            started = time.monotonic()
            on_progress(run)
            stored_at = time.monotonic()
            store_s = stored_at - started
        if on_cell is not None:
            for cell in cells:
                on_cell(cell, len(items))

    def measured(item: ValidationItem, brun: BenchRun) -> list[dict[str, Any]]:
        cells = measured_cells(item, brun)
        mark_no_injection(cells, nothing)
        return cells

    def measured_cells(item: ValidationItem, brun: BenchRun) -> list[dict[str, Any]]:
        if item.kind != "runup":
            return [
                {
                    **new_cell(item.op, item.kind),
                    "status": "measured",
                    "error": None,
                    **measure_point(brun, item.op, options, tuple(m.orders[1:])),
                }
            ]
        assert item.speed_range is not None
        bins, plant_s, reused = measure_runup_pair(
            brun,
            settings,
            item.op.torque_nm,
            item.op.udc_v,
            item.speed_range,
            options.runup_rate_rpm_per_s,
            options.target_db,
            uncompensated,
        )
        run.runup_plant_time_s += plant_s
        run.runups_reused += int(reused)
        if not bins:
            raise MeasurementError("no speed bin of the run-up pair could be judged (the order was not fitted)")
        return bins

    # taken from an earlier validation: found before the bench runs, and added without a store each (a refined
    # map's thousands of reused points must not hold the run's loop, which the bench watchdog times)
    earlier = {} if reuse is None else {k: cells for k, item in enumerate(items) if (cells := reuse(item)) is not None}
    i = 0
    while i < len(items) and run.state == "done":
        if cancel.is_set():
            run.state, run.error = "cancelled", "cancelled by the operator"
            break
        cell = None
        try:
            with bench.run(h, decoupling=decoupling, cancel=cancel) as brun:
                while i < len(items) and not cancel.is_set():
                    item = items[i]
                    if i in earlier:
                        run.items_reused += 1
                        run.cells.extend(earlier[i])  # stored with the next point measured, or at the end
                        i += 1
                        continue
                    cell = new_cell(item.op, item.kind)
                    if item.not_run is not None:  # never run where the envelope model says the drive cannot hold it
                        cell.update(status="not_measured", error=item.not_run)
                        finish(cell)
                        cell = None
                        i += 1
                        continue
                    try:
                        finish(*measured(item, brun))
                    except (MeasurementError, ValueError) as exc:
                        # this point could not be measured; the bench is fine: the run goes on
                        cell.update(status="failed", error=f"{type(exc).__name__}: {exc}")
                        finish(cell)
                    cell = None
                    i += 1
        except RunCancelled:
            run.state, run.error = "cancelled", "cancelled by the operator"
        except InterlockTripped as exc:
            run.state, run.error = "failed", f"interlock tripped at {items[min(i, len(items) - 1)].op.label()}: {exc}"
            if cell is not None:
                cell.update(status="failed", error=f"InterlockTripped: {exc}")
                finish(cell)
                i += 1
        except Exception as exc:  # noqa: BLE001 - the bench failed at this point: the point's result, then a new run
            if cancel.is_set():
                run.state, run.error = "cancelled", "cancelled by the operator"
            elif cell is None:
                raise
            else:
                cell.update(status="failed", error=f"{type(exc).__name__}: {exc}")
                finish(cell)
                i += 1
    for item in items[i:]:
        cell = new_cell(item.op, item.kind)
        why = "the validation was cancelled" if run.state == "cancelled" else f"the validation stopped ({run.error})"
        cell.update(status="not_measured", error=f"not measured: {why}")
        finish(cell)
    return run


@dataclass(frozen=True)
class ValidationItem:
    """One thing a validation measures: a point of the finer grid (kind grid | midpoint) or the pair of run-ups
    at one torque (kind runup: `op` at the range's first speed); `not_run`: why it is not run (envelope)."""

    op: OperatingPoint
    kind: str
    not_run: str | None = None
    speed_range: tuple[float, float] | None = None


def validation_items(
    axes: dict[str, list[float]], settings: Settings, options: ValidationOptions
) -> list[ValidationItem]:
    """The points of the finer grid, then (options.runups) a run-up pair per torque of the finer torque axis and
    U_dc (service/runs/runup_validation.py)."""
    items = [
        ValidationItem(op, kind, outside_envelope(op, settings, options.override_envelope_model))
        for op, kind in validation_points(axes)
    ]
    if not options.runups:
        return items
    for udc_v in axes["udc_v"]:
        for torque_nm, _row in runup_torques(axes["torque_nm"], options.runup_torques_max):
            speed_range = runup_range(torque_nm, udc_v, axes["speed_rpm"], settings, options.override_envelope_model)
            start = OperatingPoint(torque_nm=torque_nm, speed_rpm=min(axes["speed_rpm"]), udc_v=udc_v)
            not_run = (
                None
                if speed_range is not None
                else (
                    f"not run: the envelope model of the motor settings holds {torque_nm:g} Nm nowhere in the map's "
                    "speed range"
                )
            )
            items.append(ValidationItem(start, "runup", not_run, speed_range))
    return items


def judged_points(cells: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Every judged point (grid, midpoints, run-up bins) against the validation's target (DESIGN section 6): measured,
    with a verdict (`holds`); a summary's `points`, of which `held` hold."""
    return [c for c in cells if c["status"] == "measured" and c.get("holds") is not None]


def summarize(cells: list[dict[str, Any]], harmonic_order: int | None = None) -> dict[str, Any]:
    """Median and minimum suppression of the grid and of the midpoint cells measured, the worst cell,
    and the counts (failed and not measured cells count apart, never as a number); a map of several orders adds
    `orders`, each order's figures (the first: `harmonic_order`, the map's own)."""
    out: dict[str, Any] = {}
    for kind in ("grid", "midpoint", "runup"):
        mine = [c for c in cells if c["kind"] == kind]
        values = [c["suppression_db"] for c in mine if c["status"] == "measured"]
        out[kind] = {
            "cells": len(mine),
            "measured": len(values),
            "failed": sum(1 for c in mine if c["status"] == "failed"),
            "not_measured": sum(1 for c in mine if c["status"] == "not_measured"),
            "at_noise_floor": sum(1 for c in mine if c.get("at_noise_floor")),
            "median_db": statistics.median(values) if values else None,
            "min_db": min(values) if values else None,
        }
    measured = [c for c in cells if c["status"] == "measured"]
    worst = min(measured, key=lambda c: c["suppression_db"]) if measured else None
    out["worst"] = (
        None
        if worst is None
        else {
            "operating_point": worst["operating_point"],
            "kind": worst["kind"],
            "suppression_db": worst["suppression_db"],
        }
    )
    # bench seconds: each point's settling and measurement (plant time; a failed point's cost is not known here)
    out["settle_plant_s"] = sum(c.get("settle_plant_s") or 0.0 for c in measured)
    out["plant_time_s"] = out["settle_plant_s"] + sum(c.get("plant_time_s") or 0.0 for c in measured)
    judged = judged_points(cells)
    values = [c["suppression_db"] for c in judged]
    out["points"] = len(judged)
    out["held"] = sum(1 for c in judged if c["holds"])
    out["median_db"] = statistics.median(values) if values else None
    out["min_db"] = min(values) if values else None
    # judged where the drive injects nothing (runup_validation.mark_no_injection): no compensation, never harm
    out["no_injection"] = sum(1 for c in judged if c.get("no_injection"))
    out["torques_run_up"] = sorted({c["operating_point"]["torque_nm"] for c in measured if c["kind"] == "runup"})
    further = sorted({o["order"] for c in measured for o in c.get("orders") or []})
    if further:  # a map of several orders: every order judged on its own (the first is the figures above)
        out["orders"] = [
            _order_summary(harmonic_order, measured, own=True),
            *(
                _order_summary(h, [o for c in measured for o in c.get("orders") or [] if o["order"] == h])
                for h in further
            ),
        ]
    return out


def _order_summary(order: int | None, figures: list[dict[str, Any]], own: bool = False) -> dict[str, Any]:
    """An order's points, held, median and minimum over the judged figures (`own`: the map's own order, the cells'
    top-level figures at the grid and midpoint points, where the further orders are judged too)."""
    judged = [f for f in figures if f.get("suppression_db") is not None and not (own and f["kind"] == "runup")]
    values = [f["suppression_db"] for f in judged]
    return {
        "order": order,
        "points": len(judged),
        "held": sum(1 for f in judged if f["holds"]),
        "median_db": statistics.median(values) if values else None,
        "min_db": min(values) if values else None,
    }


def store_validation(
    storage: Storage, job_id: int, run: ValidationRun, bench_identity: str, finished: bool = True
) -> int:
    """The run into its map_validations row (inserted the first time, updated after): `finished` False
    while it runs (state running), so a crash keeps every point measured so far. Returns the row id."""
    fields = {
        "state": run.state if finished else "running",
        "error": run.error,
        "summary": run.summary(),
        "cells": run.cells,
        "download": run.download,
        "finished_at": now_iso() if finished else None,
    }
    if run.row_id is None:
        run.row_id = storage.insert_validation(
            {
                "map_id": run.map_id,
                "job_id": job_id,
                "harmonic_order": run.harmonic_order,
                "options": run.options,
                "bench_identity": bench_identity,
                "software_version": __version__,
                "started_at": run.started_at,
                **fields,
            }
        )
    else:
        storage.update_validation(run.row_id, **fields)
    return run.row_id


def check_points(axes: dict[str, list[float]], settings: Settings, override_envelope_model: bool = False) -> None:
    """Every point of the finer grid of the map's axes within the bench's limits, and at least one within the
    envelope model unless overridden (before anything is queued); the points outside it are not measured
    (run_validation: a cell `not_measured` with the reason)."""
    points = [op for op, _kind in validation_points(axes)]
    for op in points:
        check_limits(op, settings)
    check_any_inside(points, settings, override_envelope_model)
