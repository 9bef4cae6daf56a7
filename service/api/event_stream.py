"""The body of GET /events: one subscriber's Server-Sent Events until the client goes or the service
shuts down (EventBroker.close), with a keep-alive comment when nothing happens for a while."""

from __future__ import annotations

import asyncio
import json
from typing import AsyncIterator

from fastapi import Request

from service.api.public.results import result_public
from service.runs.events import END, format_sse

KEEP_ALIVE_S = 15.0  # a comment line this often keeps proxies and browsers from closing a quiet stream


async def event_stream(request: Request, service, token) -> AsyncIterator[str]:
    """The events of the subscription `token` (service.broker.subscribe()), which it ends when it ends."""
    _, queue = token
    try:
        yield format_sse("bench.status", json.dumps(service.bench.status(), default=str))
        while not service.broker.closed:
            if await request.is_disconnected():
                break
            try:
                event_type, data = await asyncio.wait_for(queue.get(), timeout=KEEP_ALIVE_S)
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


def _with_result(service, data: str) -> str:
    """A sweep point names its result by id (the runs keep no public shapes): shown here as the API
    shows a result in a list, without traces."""
    point = json.loads(data)
    rid = point.pop("result_id", None)
    row = service.records.get_result(rid) if rid is not None else None
    point["result"] = result_public(row, with_traces=False).model_dump() if row is not None else None
    return json.dumps(point, default=str)
