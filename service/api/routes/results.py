"""Stored results, one per identification (and per point of a sweep), and their raw recordings."""

from __future__ import annotations

import os
from typing import Literal

from fastapi import APIRouter, HTTPException, Query, status
from fastapi.responses import StreamingResponse

from service.api.deps import ResourceId, ServiceDep
from service.api.errors import error_responses
from service.api.public.results import ResultPublic, result_public
from service.store.recordings import RECORDING_FORMATS

router = APIRouter(prefix="/api/v1", tags=["results"])

RecordingFormatName = Literal[tuple(RECORDING_FORMATS)]


@router.get("/results/{result_id}", response_model=ResultPublic, responses=error_responses(404))
def get_result(result_id: ResourceId, service: ServiceDep) -> ResultPublic:
    row = service.records.get_result(result_id)
    if row is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"result {result_id} does not exist")
    return result_public(row)


@router.get(
    "/results/{result_id}/recording",
    response_class=StreamingResponse,
    responses={
        200: {
            "description": "the raw recording (DAQ samples and theta setpoints)",
            "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}},
        },
        **error_responses(404),
    },
)
def get_recording(
    result_id: ResourceId,
    service: ServiceDep,
    format: RecordingFormatName = Query(
        "mf4", description=" | ".join(f"{name}: {what}" for name, what in RECORDING_FORMATS.items())
    ),
) -> StreamingResponse:
    """The result's raw recording; 404 says why there is none (never written, write failed, deleted by
    retention, missing: its file deleted or moved behind the service's back), naming the result, never a
    path on the server."""
    handle = service.open_recording(result_id)  # RecordingUnavailable: a 404 saying why

    def chunks():
        with handle:
            while block := handle.read(1 << 20):
                yield block

    return StreamingResponse(
        chunks(),
        media_type="application/octet-stream",
        headers={
            "Content-Length": str(os.fstat(handle.fileno()).st_size),
            "Content-Disposition": f'attachment; filename="ripplecal_result{result_id}.{format}"',
        },
    )
