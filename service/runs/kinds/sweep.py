"""Job kind `sweep`: a grid of operating points measured in continuous bench runs, and its map
(the run body: service/runs/sweep_run.py). The grid is planned once, at submit (`plan_grid`: speeds
placed around the predicted field-weakening onset); the planned grid is what the sweep stores, and its
run and its checks read the stored grid (`stored_plan`) instead of planning again."""

from __future__ import annotations

from typing import Callable

from service import __version__
from service.identification.common import MethodOptions
from service.runs.identify import check_plant_time
from service.runs.kinds.host import JobHost, JobKind
from service.runs.plans import (
    Grid,
    PlannedGrid,
    RegimeError,
    RegimePlacement,
    SweepPlan,
    check_grid_limits,
    plan_grid,
)
from service.runs.sweep_run import job_sweep_id, stored_plan, stored_sweep
from service.store.records import JobRecord, SweepRecord


def submit(
    host: JobHost,
    grid: Grid,
    method: str,
    options: MethodOptions,
    schedule_id: int | None = None,
    regime: RegimePlacement | None = None,
    bench: str | None = None,
    planned: PlannedGrid | None = None,
) -> int:
    """Queue a sweep over the planned grid: `grid` with the speeds `regime` (service.runs.plans.RegimePlacement)
    places around the predicted field-weakening onset (service.runs.plans.plan_grid, the grid POST
    /sweeps/preview shows); `planned`: that plan, made already by the caller (POST /sweeps checks its size),
    so it is not made twice. The planned grid is what the sweep stores, so its run and its map use the
    real axes. For another bench (`bench`) the grid is stored as given (its own service places and
    checks it against its settings when it takes the sweep; a regime placement needs that bench's
    machine: refused here)."""
    own = host.is_own(bench)
    if own:
        check_grid_limits(grid, host.settings)  # each value against this bench's limits, named by its axis
        host.bench.check_reachable()
        grid = (planned or plan_grid(grid, regime, host.settings)).grid
    elif regime is not None:
        raise RegimeError(f"regime placement needs bench {bench}'s machine settings: post it to its service")
    plan = SweepPlan.from_grid(grid)
    if own:
        check_plant_time(grid.speed_rpm, method, options, host.settings)
        # every setpoint checked before the first frame
        plan.dry_run(host.settings, options.override_envelope_model)
    sweep_id = host.storage.create_sweep(
        method,
        host.settings.identification.harmonic_order,
        grid.model_dump(),
        options.model_dump(),
        len(plan.points),
        host.bench.identity if own else f"bench {bench}",  # its service writes the identity when it starts it
        __version__,
        schedule_id=schedule_id,
        bench=host.bench_name if own else bench,
    )
    host.queue_sweep(sweep_id)
    return sweep_id


def check_first_take(host: JobHost, job: JobRecord, check: Callable[[SweepRecord, bool], None]) -> None:
    """A sweep (of any kind) queued by another bench's service and not yet started here: `check(sweep,
    override)` against this bench's settings, then the sweep takes this bench's identity."""
    sweep_id = job_sweep_id(job)
    sweep = stored_sweep(host.storage, sweep_id)
    if sweep["started_at"] is None and sweep["bench_identity"] != host.bench.identity:
        check(sweep, bool(sweep["options"].get("override_envelope_model", False)))
        host.storage.update_sweep(sweep_id, bench_identity=host.bench.identity)


def check_here(host: JobHost, job: JobRecord) -> None:
    check_first_take(host, job, lambda sweep, override: stored_plan(sweep).dry_run(host.settings, override))


def run(host: JobHost, job_id: int, job: JobRecord) -> None:
    sweep_id = job_sweep_id(job)
    host.sweeps.run_sweep(job_id, sweep_id, host.control(sweep_id))


KIND = JobKind("sweep", submit=submit, check_here=check_here, run=run)
