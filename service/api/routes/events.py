"""Server-Sent Events: bench status, job and sweep progress, interlock trips, as they happen.
A stream ends when the service shuts down (EventBroker.close), so one Ctrl+C stops it."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import StreamingResponse

from service.api.deps import ServiceDep
from service.api.event_stream import event_stream

router = APIRouter(prefix="/api/v1", tags=["events"])


@router.get("/events")
async def events(request: Request, service: ServiceDep) -> StreamingResponse:
    token = service.broker.subscribe()  # subscribed now: nothing published from here on is missed
    return StreamingResponse(
        event_stream(request, service, token),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )
