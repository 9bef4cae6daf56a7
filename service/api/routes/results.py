"""Stored results, one per identification (and per point of a sweep)."""
from __future__ import annotations

from fastapi import APIRouter, HTTPException, status

from service.api.deps import ResourceId, ServiceDep
from service.api.errors import error_responses
from service.public import ResultPublic, result_public

router = APIRouter(prefix="/api/v1", tags=["results"])


@router.get("/results/{result_id}", response_model=ResultPublic, responses=error_responses(404))
def get_result(result_id: ResourceId, service: ServiceDep) -> ResultPublic:
    row = service.storage.get_result(result_id)
    if row is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"result {result_id} does not exist")
    return result_public(row)
