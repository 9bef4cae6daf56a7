"""Bench: its live status, the software version, and the fault reset a person acknowledges."""

from __future__ import annotations

from fastapi import APIRouter

from service.api.deps import OperatorDep, ServiceDep
from service.api.errors import error_responses
from service.api.public.benches import BenchPublic, bench_public

router = APIRouter(prefix="/api/v1", tags=["bench"])


@router.get("/bench/status")
def bench_status(service: ServiceDep) -> dict:
    """Per device: connected, last error, age; the interlocks; whether a run holds the bench."""
    return service.bench.status()


@router.get("/benches", response_model=list[BenchPublic])
def benches(service: ServiceDep) -> list[BenchPublic]:
    """Every bench of the lab (one service per bench, one database): online, state, what it runs, its queue."""
    return [bench_public(b) for b in service.lab.overview()]


@router.get("/version")
def version(service: ServiceDep) -> dict:
    return {
        "software_version": service.version,
        "bench": service.bench.identity,
        "bench_name": service.settings.bench_name,
    }


@router.post("/bench/fault-reset", responses=error_responses(401, 403, 409, 502))
def fault_reset(service: ServiceDep, _: OperatorDep) -> dict:
    """Acknowledge a drive/load FAULT (CiA 402 fault reset) and clear the latched interlocks whose
    condition has gone. The service never does this by itself (unless `interlocks.auto_fault_reset`).
    Answers what was reset, what still forbids a run (`still_tripped`), and the bench status."""
    result = service.fault_reset()  # 409 busy or a device still braking, 502 it failed (the service says which)
    return {**result, "status": service.bench.status()}
