"""Request body size limit as pure ASGI middleware: it runs before routing, parsing and authentication,
so an oversized body (declared by Content-Length, or streamed chunked without one) costs nothing."""

from __future__ import annotations

import json


class _BodyTooLarge(Exception):
    pass


class BodySizeLimit:
    def __init__(self, app, max_body_bytes: int):
        self.app = app
        self.max_body_bytes = max_body_bytes

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None:
            try:
                length = int(declared)
            except ValueError:
                await self._refuse(send, 400, f"Content-Length {declared.decode(errors='replace')!r} is not a number")
                return
            if length > self.max_body_bytes:
                await self._refuse(send, 413, self._too_large_text(f"Content-Length {length}"))
                return

        received = 0
        too_large = False
        started = False

        async def counted_receive():
            nonlocal received, too_large
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_body_bytes:
                    too_large = True
                    raise _BodyTooLarge()
            return message

        async def guarded_send(message):
            nonlocal started
            if too_large:
                return  # whatever the app makes of a cut-off body is replaced by the 413 below
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, counted_receive, guarded_send)
        except Exception:
            # FastAPI turns a failed body read into its own 400; either way the body was too large
            if not too_large:
                raise
        if too_large and not started:
            await self._refuse(send, 413, self._too_large_text(f"streamed body of more than {received} bytes"))

    def _too_large_text(self, what: str) -> str:
        return f"request body too large: {what}, limit {self.max_body_bytes} bytes (server.max_body_bytes)"

    @staticmethod
    async def _refuse(send, status: int, detail: str) -> None:
        body = json.dumps({"detail": detail}).encode()
        await send(
            {
                "type": "http.response.start",
                "status": status,
                "headers": [
                    (b"content-type", b"application/json"),
                    (b"content-length", str(len(body)).encode()),
                    (b"connection", b"close"),
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})
