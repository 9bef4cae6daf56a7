"""Bench: its live status, the software version, and the fault reset a person acknowledges."""

from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field

from service.api.deps import OperatorDep, ServiceDep
from service.api.errors import error_responses
from service.api.public.benches import BenchPublic, bench_public

router = APIRouter(prefix="/api/v1", tags=["bench"])


@router.get("/bench/status")
def bench_status(service: ServiceDep) -> dict:
    """Per device: connected, last error, age; the interlocks; whether a run holds the bench."""
    return service.bench.status()


class CheckLinePublic(BaseModel):
    name: str
    ok: bool
    detail: str = Field(description="what the check found")
    fix: str | None = Field(None, description="what to change when it did not pass")


class BenchCheckPublic(BaseModel):
    ok: bool = Field(description="every check passed")
    spin: bool = Field(description="the shaft was turned for the angle, accelerometer and sync-line checks")
    checks: list[CheckLinePublic]


class BenchCheckCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    spin: bool = Field(
        True, description="turn the shaft slowly without torque (interlocked, safe at the end) for the spin checks"
    )


@router.get("/bench/check", response_model=BenchCheckPublic, responses=error_responses(409))
def bench_check(service: ServiceDep) -> dict:
    """The bring-up check, reading only: links, node identities and heartbeats, the DAQ line, the supply
    (POST with spin for the checks a turning shaft needs). 409 while a run holds the bench."""
    return service.bench_check(spin=False)


@router.post("/bench/check", response_model=BenchCheckPublic, responses=error_responses(400, 401, 403, 409, 413))
def bench_check_spin(body: BenchCheckCreate, service: ServiceDep, _: OperatorDep) -> dict:
    """The bring-up check with a slow spin (operator: the shaft turns): also the angle's sign and rate against
    velocity actual and pole pairs, the accelerometer, the sync line."""
    return service.bench_check(spin=body.spin)


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
