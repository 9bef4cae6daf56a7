"""Server-Sent Events: bench status, job and sweep progress, interlock trips, as they happen.
A stream ends when the service shuts down (EventBroker.close), so one Ctrl+C stops it."""

from __future__ import annotations

import asyncio
import json

from fastapi import APIRouter, Request
from fastapi.responses import StreamingResponse

from service.api.deps import ServiceDep
from service.api.public import result_public
from service.runs.events import END, format_sse

router = APIRouter(prefix="/api/v1", tags=["events"])


@router.get("/events")
async def events(request: Request, service: ServiceDep) -> StreamingResponse:
    token = service.broker.subscribe()
    _, queue = token

    async def stream():
        try:
            yield format_sse("bench.status", json.dumps(service.bench_status(), default=str))
            while not service.broker.closed:
                if await request.is_disconnected():
                    break
                try:
                    event_type, data = await asyncio.wait_for(queue.get(), timeout=15.0)
                except asyncio.TimeoutError:
                    yield ": keep-alive\n\n"
                    continue
                if (event_type, data) == END:  # the service is shutting down
                    break
                if event_type == "sweep.point":
                    data = _with_result(service, data)
                yield format_sse(event_type, data)
        finally:
            service.broker.unsubscribe(token)

    return StreamingResponse(
        stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}
    )


def _with_result(service, data: str) -> str:
    """A sweep point names its result by id (the runs keep no public shapes): shown here as the API
    shows a result in a list, without traces."""
    point = json.loads(data)
    rid = point.pop("result_id", None)
    row = service.get_result(rid) if rid is not None else None
    point["result"] = result_public(row, with_traces=False).model_dump() if row is not None else None
    return json.dumps(point, default=str)
