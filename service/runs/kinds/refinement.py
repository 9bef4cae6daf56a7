"""Job kind `refinement`: a map refined in rounds (service/runs/refinement.py plans them), queued as a
sweep of kind `refinement`: its cells, pause, resume, cancel and crash-resume are a sweep's. Its run
body measures a round's cells through the sweep's (service/runs/sweep_run.py SweepRunner.measure_points)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, cast

from service import __version__
from service.errors import NotFound
from service.identification.common import MethodOptions
from service.maps.build import build_map
from service.maps.lut_export import SPARSE, cell_count, injection_unchanged, lut_image, map_interpolation
from service.maps.placement import (
    MAX_PLACE_ROUNDS,
    Cell,
    axes_with,
    bend_db,
    candidate_cells,
    cells_to_measure,
    first_candidates,
    grid_bytes,
    judge_candidates,
    place,
    worst_db,
)
from service.maps.view import map_view
from service.model.operating_point import OperatingPoint
from service.runs.identify import check_plant_time, parse_options
from service.runs.kinds.host import JobHost, JobKind
from service.runs.kinds.sweep import check_first_take
from service.runs.plans import Grid, settling_order
from service.runs.refinement import (
    CELL_S,
    MAX_GUARD_ROUNDS,
    MAX_ROUNDS,
    REFINED_INTERPOLATION,
    VALIDATION_POINT_S,
    BenchBudget,
    RefinementState,
    RefineRequest,
    check_request,
    guard_cells,
    harmful_points,
    no_progress,
    plan_round,
    point_cost_s,
    reuse_where,
)
from service.runs.states import Cancelled, Paused, SweepControl, SweepState
from service.runs.sweep_run import SweepRunner, job_sweep_id, stored_sweep
from service.runs.validation import (
    ValidationItem,
    ValidationOptions,
    check_points,
    run_validation,
    store_validation,
)
from service.store.records import JobRecord, MapRecord, ResultRecord, SweepRecord, bench_plant_s
from service.store.storage import now_iso


def submit(host: JobHost, map_id: int, request: RefineRequest, bench: str | None = None) -> int:
    """Refused before anything is queued: KeyError (no such map), ValueError (method or options),
    LimitError (a validation point outside the bench's limits). A partial map is accepted: its non-ok
    cells are measured first. Returns the job's id."""
    own = host.is_own(bench)
    if own:
        host.bench.check_reachable()
    m = map_view(host.storage, map_id)
    if m is None:
        raise KeyError(map_id)
    check_request(request)
    options = parse_options(request.method, request.options)
    if own:
        # a refinement measures cells (its method options) and validates (its validation options)
        check_points(
            m.axes,
            host.settings,
            options.override_envelope_model and request.validation.override_envelope_model,
        )
        check_plant_time(m.axes["speed_rpm"], request.method, options, host.settings)
    not_ok = [[c.torque_nm, c.speed_rpm, c.udc_v] for c in m.cells if c.status != "ok"]
    candidates = first_candidates(m.axes) if request.placement == "curves" else {}
    lines = candidate_cells(m.axes, candidates)
    if len(not_ok) + len(lines) > request.max_cells:
        candidates, lines = {}, []  # the first bisection does not fit the cell budget: insert where validations fail
    pending = not_ok + [list(c) for c in lines]
    state: RefinementState = {
        "target_db": request.target_db,
        "max_cells": request.max_cells,
        "validation": request.validation.model_dump(),
        "phase": "measure" if pending else "validate",
        "round": 0,
        "current_map_id": map_id,
        "axes": m.axes,
        "pending": pending,
        "cells_added": 0,
        "rounds": [],
        "stopped": None,
        "max_bytes": request.max_bytes,
        "max_bench_s": request.max_bench_s,
        "plant_time_s": 0.0,
        "round_plant_s": 0.0,
        "candidates": candidates,
        "lut_cells": request.lut_cells,
    }
    sweep_id = host.storage.create_sweep(
        request.method,
        m.harmonic_order,
        m.axes,
        options.model_dump(),
        len(pending),
        host.bench.identity if own else f"bench {bench}",
        __version__,
        kind="refinement",
        source_map_id=map_id,
        refinement=dict(state),  # the column takes a plain dict
        bench=host.bench_name if own else bench,
    )
    return host.queue_sweep(sweep_id)


def check_here(host: JobHost, job: JobRecord) -> None:
    def check(sweep: SweepRecord, override: bool) -> None:
        validation = (sweep.get("refinement") or {}).get("validation") or {}
        override = override and bool(validation.get("override_envelope_model", False))
        check_points(sweep["grid"], host.settings, override)

    check_first_take(host, job, check)


def run(host: JobHost, job_id: int, job: JobRecord) -> None:
    sweep_id = job_sweep_id(job)
    RefinementRun(host.sweeps).run_refinement(job_id, sweep_id, host.control(sweep_id))


def saved_state(sweep: SweepRecord) -> RefinementState:
    """Where the refinement stood at its last saved step (its sweep's `refinement` column)."""
    state = sweep["refinement"]
    if state is None:
        raise ValueError(f"sweep {sweep['id']} of kind {sweep['kind']} holds no refinement state")
    return cast(RefinementState, state)  # the JSON column as submit and _save_refinement wrote it


def _interpolation(state: RefinementState, source: MapRecord) -> str:
    """The drive's interpolation the refinement places and validates in: its validation's, else the source map's
    own (a refined map's), else REFINED_INTERPOLATION (cubic; an int11-sparse LUT, which cubic cannot be: the
    drive's default)."""
    named = ValidationOptions.model_validate(state["validation"]).interpolation
    if named is None and "interpolation" not in (source.get("provenance") or {}) and state.get("lut_cells") != SPARSE:
        named = REFINED_INTERPOLATION
    return map_interpolation(dict(source), named)


class RefinementRun:
    """A refinement's rounds, measured through a sweep's runner."""

    def __init__(self, runner: SweepRunner):
        self.runner, self.host = runner, runner.host
        # the uncompensated run-ups of this refinement's validations (one bench, one range): measured once
        self.uncompensated: dict[tuple[float, ...], dict[str, Any]] = {}
        self.storage, self.bench, self.settings, self.broker = (
            runner.storage,
            runner.bench,
            runner.settings,
            runner.broker,
        )

    def run_refinement(self, job_id: int, sweep_id: int, ctl: SweepControl) -> None:
        """A refinement's rounds (service/runs/refinement.py): measure the pending cells, build the refined map,
        validate it in the drive's LUT mode, plan the next cells; its state is saved after every step,
        so a resume (after a pause, an interlock or a crash) goes on from where it stood."""
        sweep = stored_sweep(self.storage, sweep_id)
        state = saved_state(sweep)
        options = parse_options(sweep["method"], sweep["options"])
        if ctl.cancel.is_set() or SweepState(sweep["state"]) == SweepState.CANCELLED:
            raise Cancelled()
        if ctl.pause.is_set():
            raise Paused()
        self.host.set_sweep(
            sweep_id, SweepState.RUNNING, started_at=sweep["started_at"] or now_iso(), pause_reason=None
        )
        source_map_id = sweep["source_map_id"]
        source = self.storage.get_map(source_map_id) if source_map_id is not None else None
        if source is None:
            raise NotFound(f"refinement {sweep_id}: its source map {source_map_id} does not exist")
        while state["phase"] != "done":
            if ctl.cancel.is_set():
                break
            if ctl.pause.is_set():
                raise Paused()
            if state["phase"] == "measure":
                self._refinement_measure(sweep_id, sweep, ctl, options, state, source)
            elif state["phase"] == "place":
                self._refinement_place(sweep_id, sweep, state, source)
            elif state["phase"] == "guard":
                self._refinement_guard(sweep_id, sweep, state, source)
            else:
                self._refinement_validate(job_id, sweep_id, ctl, state)
            self._save_refinement(sweep_id, state)
        if self.host.shutting_down():
            self.host.set_sweep(
                sweep_id,
                SweepState.INTERRUPTED,
                pause_reason=f"{self.host.shutdown_reason} during round {state['round']} ({state['phase']}); "
                "resume to go on from there",
            )
            return
        final = SweepState.CANCELLED if ctl.cancel.is_set() else SweepState.DONE
        self.host.set_sweep(sweep_id, final, finished_at=now_iso(), map_id=state["current_map_id"])

    def _refinement_rows(self, sweep_id: int, source: MapRecord) -> list[ResultRecord]:
        """The source map's results, then the refinement's own (a later one for the same cell wins)."""
        ids = [c["result_id"] for c in source["cells"] if c["result_id"] is not None]
        return list(self.storage.results_by_id(ids).values()) + self.storage.sweep_results(sweep_id)

    def _refinement_measure(
        self,
        sweep_id: int,
        sweep: SweepRecord,
        ctl: SweepControl,
        options: MethodOptions,
        state: RefinementState,
        source: MapRecord,
    ) -> None:
        """Identify the round's pending cells (those not yet measured in this round), then judge the placement
        candidates among them (phase place) or build the refined map from every result and move on to its
        validation."""
        measured = {(r["torque_nm"], r["speed_rpm"], r["udc_v"]) for r in self._round_results(sweep_id, state)}
        points = settling_order(
            [
                OperatingPoint(torque_nm=t, speed_rpm=n, udc_v=u)
                for t, n, u in state["pending"]
                if (t, n, u) not in measured
            ]
        )
        grid = Grid(**axes_with(state["axes"], state.get("candidates") or {}))
        self._publish_refinement(sweep_id, state, f"measuring {len(points)} cell(s)")
        self.runner.measure_points(
            sweep_id,
            sweep,
            ctl,
            grid,
            options,
            points,
            sweep_pass=1,
            neighbour_rows=lambda: self._refinement_rows(sweep_id, source),
            tags={"refinement_round": state["round"]},
        )
        if ctl.cancel.is_set():
            return
        state["round_plant_s"] = sum(bench_plant_s(r) for r in self._round_results(sweep_id, state))
        state["cells_added"] += len(state["pending"])  # the round's cells, also those measured before a crash
        if state.get("candidates"):
            state["phase"] = "place"  # the candidates' lines are judged before any map is built
            return
        state["current_map_id"] = self._build_round_map(sweep_id, sweep, state, source)
        state["phase"] = "validate"

    def _refinement_place(self, sweep_id: int, sweep: SweepRecord, state: RefinementState, source: MapRecord) -> None:
        """Placement from curves (service/maps/placement.py): keep the candidates whose line the drive's
        interpolation of its neighbours misses, bisect their halves next round; when nothing is left to bisect
        (or a budget is spent), build the map and validate it."""
        thetas = {}
        rows = self._refinement_rows(sweep_id, source)
        for r in rows:  # a later result for the same cell wins
            tc, ts = r.get("theta_cos"), r.get("theta_sin")
            if r["status"] == "ok" and tc is not None and ts is not None:
                thetas[(float(r["torque_nm"]), float(r["speed_rpm"]), float(r["udc_v"]))] = complex(tc, ts)
        candidates = state.get("candidates") or {}
        interpolation = _interpolation(state, source)
        judged = judge_candidates(state["axes"], candidates, thetas, interpolation)
        cells_format = state.get("lut_cells", "float32")
        round_plant_s = _close_round_plant(state)
        placed = state.setdefault("placement_rounds", [])
        measured_now = len(self._round_results(sweep_id, state))
        measured = {(float(r["torque_nm"]), float(r["speed_rpm"]), float(r["udc_v"])) for r in rows}
        budget = self._budget(state, [*placed, {"plant_time_s": round_plant_s, "measured": measured_now}])

        def affordable(grown: dict[str, list[float]]) -> str | None:
            return None if budget is None else budget.against(len(cells_to_measure(grown, {}, measured)), grown)

        kept, following, reasons = place(
            state["axes"],
            judged,
            state["target_db"],
            state.get("max_bytes"),
            cells_format,
            thetas,
            interpolation,
            affordable,
        )
        state["axes"] = axes_with(state["axes"], kept)
        placed.append(
            {
                "round": state["round"],
                "measured": measured_now,
                "candidates": {a: len(v) for a, v in candidates.items()},
                "inserted": kept,
                "worst_predicted_db": worst_db(judged),
                "bytes": grid_bytes(state["axes"], thetas, cells_format, interpolation),
                "cells": cell_count(state["axes"]),
                "plant_time_s": round_plant_s,
                "left_out": reasons,
            }
        )
        if budget is not None:  # only the candidates whose lines, and the grid's validation with them, fit
            following = affordable_candidates(budget, state["axes"], following, measured, thetas)
        pending = cells_to_measure(state["axes"], following, measured)
        if not (
            any(following.values())
            and len(placed) < MAX_PLACE_ROUNDS
            and state["cells_added"] + len(pending) <= state["max_cells"]
            and (budget is None or budget.against(len(pending), state["axes"]) is None)
        ):
            # placement ends; the cells of the grid not measured yet (where two kept values cross) still are
            following, pending = {}, cells_to_measure(state["axes"], {}, measured)
        state["candidates"], state["pending"] = following, [list(c) for c in pending]
        if pending or any(following.values()):  # candidates with every cell measured are judged next round as they are
            state["round"] += 1
            state["phase"] = "measure"
            return
        state["current_map_id"] = self._build_round_map(sweep_id, sweep, state, source, placement="curves")
        state["round"] += 1
        state["phase"] = "validate"

    def _round_results(self, sweep_id: int, state: RefinementState) -> list[ResultRecord]:
        """The refinement's results measured in its current round (tagged refinement_round)."""
        return [
            r
            for r in self.storage.sweep_results(sweep_id)
            if ((r.get("detail") or {}).get("details") or {}).get("refinement_round") == state["round"]
        ]

    def _build_round_map(
        self, sweep_id: int, sweep: SweepRecord, state: RefinementState, source: MapRecord, **provenance: Any
    ) -> int:
        """The round's map from every result so far (the source map's, then the refinement's), naming where it
        comes from."""
        return build_map(
            self.storage,
            state["axes"],
            self._refinement_rows(sweep_id, source),
            sweep_id,
            sweep["harmonic_order"],
            sweep["method"],
            self.bench.identity,
            refined_from=sweep["source_map_id"],
            provenance={
                "refinement_id": sweep_id,
                "source_map_id": sweep["source_map_id"],
                "round": state["round"],
                "cells_added": state["cells_added"],
                "lut_cells": state.get("lut_cells", "float32"),
                "lut_max_bytes": state.get("max_bytes"),  # a version 7 image is made to fit (lut_export.lut_image)
                # placed and validated in it: its downloads and exports use it unless they name another
                "interpolation": _interpolation(state, source),
                **provenance,
            },
        )

    def _refinement_validate(self, job_id: int, sweep_id: int, ctl: SweepControl, state: RefinementState) -> None:
        """Validate the current map in the drive's LUT mode; plan the next round, or end."""
        map_id = state["current_map_id"]
        self._publish_refinement(sweep_id, state, f"validating map {map_id}")

        def on_cell(cell: dict[str, Any], total: int) -> None:
            self.broker.publish(
                "job.progress",
                {"job_id": job_id, "kind": "refinement", "round": state["round"], "total": total, "cell": cell},
            )

        options = ValidationOptions.model_validate(state["validation"])
        run = run_validation(
            self.storage,
            self.bench,
            self.settings,
            map_id,
            True,
            options,
            ctl.cancel,
            on_cell=on_cell,
            on_progress=lambda r: store_validation(self.storage, job_id, r, self.bench.identity, finished=False),
            uncompensated=self.uncompensated,
            reuse=self._round_reuse(state, map_id, options),
        )
        validation_id = store_validation(self.storage, job_id, run, self.bench.identity)
        if run.state == "cancelled":
            return
        if run.state == "failed":
            # an interlock stopped it: pause like a sweep; on resume the map is validated again
            with self.host.lock:
                ctl.pause.set()
                self.host.set_sweep(
                    sweep_id,
                    SweepState.PAUSED,
                    pause_reason=f"{run.error} (validating refined map "
                    f"{map_id}); acknowledge with POST /api/v1/bench/fault-reset, then resume",
                )
            return
        m = map_view(self.storage, map_id)
        if m is None:
            raise NotFound(f"refinement {sweep_id}: its map {map_id} does not exist")
        plan = plan_round(
            m.axes,
            [c.model_dump() for c in m.cells],
            run.cells,
            state["target_db"],
            state["max_cells"] - state["cells_added"],
            state.get("max_bytes"),
            state.get("lut_cells", "float32"),
        )
        summary = run.summary()
        harmful = harmful_points(run.cells)
        round_plant_s = _close_round_plant(state, float(summary["plant_time_s"] or 0.0))
        state["rounds"].append(
            {
                "round": state["round"],
                "map_id": map_id,
                "validation_id": validation_id,
                "points": len(run.cells),
                "below_target": plan.failing,
                "grid_median_db": summary["grid"]["median_db"],
                "midpoint_median_db": summary["midpoint"]["median_db"],
                "min_db": summary["min_db"],  # over every judged point: grid, midpoints, run-up bins
                "inserted": plan.inserted,
                "remeasured": len(plan.remeasure),
                "new_cells": len(plan.new_cells),
                # what the user pays: firmware memory of this round's map and bench time (plant seconds)
                "bytes": len(lut_image(m.model_dump(), interpolation=options.interpolation)),
                "cells": cell_count(m.axes),
                "plant_time_s": round_plant_s,
                "point_s": point_cost_s(run.cells),  # what a stepped point cost here, plant s (the budget's next)
                "points_judged": summary.get("points"),
                "held": summary.get("held"),
                "median_db": summary.get("median_db"),
                "harmful": len(harmful),
                # judged where the drive injects nothing (cells turned off): never harm (mark_no_injection)
                "no_injection": summary.get("no_injection"),
                "injection_off": len(state.get("guard_off", [])),
            }
        )
        budget = self._budget(state, state.get("placement_rounds", []))
        guarding = state.get("guard_rounds", 0) > 0  # a guarded map is the last: its flags hold on its own axes
        stopped: str | None = None  # why the refinement ends here (None: it holds, or it goes on)
        if guarding or plan.failing == 0:
            ending = True
        elif (stalled := no_progress(state["rounds"])) is not None:
            ending, stopped = True, stalled
        elif not plan.cells:
            ending, stopped = True, plan.why_nothing_fits(state.get("max_bytes"))
            state["stopped_details"] = plan.reasons
        elif budget is not None and (over := budget.against_round(len(plan.cells), m.axes)) is not None:
            ending, stopped = True, over
        elif state["round"] + 1 >= MAX_ROUNDS:
            ending, stopped = True, f"after {MAX_ROUNDS} rounds"
        else:
            ending = False
        if not ending:
            state["axes"] = axes_with(m.axes, plan.inserted)
            state["pending"] = [list(k) for k in plan.cells]
            state["round"] += 1
            state["phase"] = "measure"
            return
        already_off = {(c[0], c[1], c[2]) for c in state.get("guard_off", [])}
        off = already_off | set(guard_cells(m.axes, [c.model_dump() for c in m.cells], harmful)) if harmful else set()
        # a guard round that would turn off no new cell would validate the same LUT again: it ends here instead
        if harmful and state.get("guard_rounds", 0) < MAX_GUARD_ROUNDS and off != already_off:
            # never worse than nothing: the drive gives no compensation where this LUT made the order worse
            state["guard_off"] = [list(c) for c in sorted(off)]
            state["phase"] = "guard"
            state["stopped"] = stopped  # kept for the guarded map's verdict
            return
        state["phase"] = "done"
        reasons = [state.get("stopped") or stopped] if plan.failing else []
        if state.get("guard_off"):
            reasons.append(
                f"injection off at {len(state['guard_off'])} cell(s) where the LUT made the order worse"
                + (f"; {len(harmful)} point(s) still worse than no compensation" if harmful else "")
            )
        state["stopped"] = (
            f"{plan.failing} point(s) still below {state['target_db']:g} dB: " + "; ".join(r for r in reasons if r)
            if plan.failing or harmful
            else None
        )

    def _budget(self, state: RefinementState, placed: list[dict[str, Any]]) -> BenchBudget | None:
        """The refinement's max_bench_s as a BenchBudget (None: none), a cell's cost measured on the placement rounds
        `placed` so far (CELL_S before any), a stepped validation point's on the refinement's latest validation that
        measured one (VALIDATION_POINT_S before any)."""
        max_bench_s = state.get("max_bench_s")
        if max_bench_s is None:
            return None
        cells = sum(r.get("measured", 0) for r in placed)
        cell_s = sum(r["plant_time_s"] for r in placed if r.get("measured")) / cells if cells else CELL_S
        point_s = next((r["point_s"] for r in reversed(state["rounds"]) if r.get("point_s")), VALIDATION_POINT_S)
        return BenchBudget(
            max_bench_s,
            state.get("plant_time_s", 0.0),
            cell_s,
            self.settings,
            ValidationOptions.model_validate(state["validation"]),
            point_s,
        )

    def _round_reuse(
        self, state: RefinementState, map_id: int, options: ValidationOptions
    ) -> Callable[[ValidationItem], list[dict[str, Any]] | None] | None:
        """A round's validation measures again only where the drive's injection differs from the map validated the
        round before (refinement.reuse_where); the first validation measures everything."""
        if not state["rounds"]:
            return None
        before_id = state["rounds"][-1]["map_id"]
        previous = self.storage.latest_validation(before_id)
        before, after = map_view(self.storage, before_id), map_view(self.storage, map_id)
        if previous is None or previous["state"] != "done" or before is None or after is None:
            return None
        same = injection_unchanged(before.model_dump(), after.model_dump(), options.fill, options.interpolation)
        return reuse_where(previous["cells"], same)

    def _refinement_guard(self, sweep_id: int, sweep: SweepRecord, state: RefinementState, source: MapRecord) -> None:
        """The current map built again as a map of its own with injection off at the guard's cells (LUT flag 3),
        then validated: the refinement's last map."""
        map_id = self._build_round_map(
            sweep_id, sweep, state, source, guard="injection off where the LUT made the order worse"
        )
        off = [(float(t), float(n), float(u)) for t, n, u in state.get("guard_off", [])]
        self.storage.set_injection_off(map_id, off)
        state["current_map_id"] = map_id
        state["guard_rounds"] = state.get("guard_rounds", 0) + 1
        state["round"] += 1
        state["phase"] = "validate"

    def _save_refinement(self, sweep_id: int, state: RefinementState) -> None:
        # total in the unit of done_points (the sweep's current results: one per cell, a cell measured again
        # counted once): the cells measured so far and the round's pending ones, so done = total at the end
        cells = {(r["torque_nm"], r["speed_rpm"], r["udc_v"]) for r in self.storage.sweep_results(sweep_id)}
        if state["phase"] == "measure":
            cells |= {(t, n, u) for t, n, u in state["pending"]}
        total = len(cells)
        self.storage.update_sweep(
            sweep_id, refinement=state, grid=state["axes"], map_id=state["current_map_id"], total_points=total
        )
        self._publish_refinement(sweep_id, state, state["phase"])

    def _publish_refinement(self, sweep_id: int, state: RefinementState, what: str) -> None:
        self.broker.publish(
            "refinement.progress",
            {
                "sweep_id": sweep_id,
                "round": state["round"],
                "phase": state["phase"],
                "what": what,
                "map_id": state["current_map_id"],
                "cells_added": state["cells_added"],
            },
        )


def affordable_candidates(
    budget: BenchBudget,
    axes: dict[str, list[float]],
    candidates: dict[str, list[float]],
    measured: set[Cell],
    thetas: dict[Cell, complex],
) -> dict[str, list[float]]:
    """The candidates whose lines the budget can measure and whose grid it can then validate, taken where theta*
    bends most on the grid first (placement.bend_db; ties: speed values first, a speed line is one cell a torque
    row). In order along the axes, a budget that holds a few lines spent them where theta* runs straight (seed 5: six
    speed lines at 1100..1825 rpm measured, all held, while the turn's 2125..2275 rpm failed 17-21 dB)."""
    bends = bend_db(axes, candidates, thetas)
    taken: dict[str, list[float]] = {axis: [] for axis in candidates}
    for _db, _torque, value, axis in sorted(
        (bends.get(axis, {}).get(value, math.inf), axis != "speed_rpm", value, axis)
        for axis, values in candidates.items()
        for value in values
    ):
        trial = {**taken, axis: sorted([*taken[axis], value])}
        if budget.against(len(cells_to_measure(axes, trial, measured)), axes_with(axes, trial)) is None:
            taken = trial
    return taken


def _close_round_plant(state: RefinementState, validation_plant_s: float = 0.0) -> float:
    """The round's bench seconds (its cells' settling and measurements, and its validation's), added to the
    refinement's."""
    round_plant_s = state.get("round_plant_s", 0.0) + validation_plant_s
    state["plant_time_s"] = state.get("plant_time_s", 0.0) + round_plant_s
    state["round_plant_s"] = 0.0
    return round_plant_s


KIND = JobKind("refinement", submit=submit, check_here=check_here, run=run)
