"""Bench routes of issue 8: a person acknowledges a drive fault (POST /bench/fault-reset)."""
from __future__ import annotations

from fastapi import APIRouter, HTTPException, status

from service.api.deps import OperatorDep, ServiceDep
from service.bench import BenchError

router = APIRouter(prefix="/api/v1", tags=["bench"])


@router.post("/bench/fault-reset", responses={401: {"description": "no or unknown bearer token"},
                                               403: {"description": "role below operator"},
                                               409: {"description": "the bench is busy with a run"},
                                               502: {"description": "the drive did not answer or did not leave FAULT"}})
def fault_reset(service: ServiceDep, _: OperatorDep) -> dict:
    """Acknowledge a drive/load FAULT (CiA 402 fault reset) and clear the latched interlocks whose
    condition has gone. The service never does this by itself (unless `interlocks.auto_fault_reset`).
    Answers what was reset, what still forbids a run (`still_tripped`), and the bench status."""
    try:
        result = service.fault_reset()
    except BenchError as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
    except Exception as exc:   # SDO timeout / the drive stayed in FAULT: say which
        raise HTTPException(status.HTTP_502_BAD_GATEWAY, f"fault reset failed: {type(exc).__name__}: {exc}") from None
    return {**result, "status": service.bench.status()}
