"""Bounded HTTP connections for `serve`: a flood of idle connections must not use up the process's open
files (then nothing answers, and every failed accept is a log line).

uvicorn's h11 protocol (0.54, `uvicorn/protocols/http/h11_impl.py`) arms its keep-alive timer only after a
response, and a byte received cancels it: a connection that connects and sends nothing, or trickles a
request head, is kept for ever; `limit_concurrency` answers 503 to requests but never closes a connection.
So, on two levels:
- the protocol (`GuardedH11Protocol`): at most `cap` connections; at the cap a new one closes the one idle
  the longest (waiting for a request head), or, when every one is in a request, is answered 503; a
  connection idle or part-way through a request head for `request_head_timeout_s` is closed;
- the listening sockets (`listening_sockets`): every accepted socket is counted until it is closed, and
  never more than `accept_limit` are open. A socket that has not reached the protocol (a TLS handshake
  that does not come: asyncio waits 60 s for one) is shut down after `request_head_timeout_s`, or after
  STUCK_S to make room over the limit; else the new one is closed at once. asyncio accepts its `backlog` connections in one go before any reaches the protocol:
  that batch is kept small, the kernel's queue long.
The limits stay below the open-file limit (raised to its hard limit at start), so the process always has
files left for its database, the bench's links and the emulator.
"""

from __future__ import annotations

import asyncio
import logging
import resource
import socket
import time
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from service.cli.startup import StartError

log = logging.getLogger("ripplecal.connections")

KERNEL_BACKLOG = 2048  # connections the kernel queues until they are accepted (uvicorn's default)
STUCK_S = 1.0  # a socket this old without a protocol is stuck in its TLS handshake (a real one takes ms)

_BUSY = (
    b"HTTP/1.1 503 Service Unavailable\r\ncontent-type: text/plain; charset=utf-8\r\nconnection: close\r\n"
    b"retry-after: 1\r\ncontent-length: 57\r\n\r\nevery connection is in a request (server.max_connections)\n"
)


def raise_open_files_limit() -> int:
    """The soft RLIMIT_NOFILE raised to the hard one (a shell's default is often 1024); the soft limit
    in force after it."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and soft < hard:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
            soft = hard
        except (ValueError, OSError):
            pass  # a container may forbid it: the limits below follow what is in force
    return soft


def connection_cap(max_connections: int, open_files_limit: int) -> int:
    """HTTP connections: at most half the open files (the accept limit adds a quarter for sockets not yet
    connections; the last quarter is the database's, the bench links', the emulator's)."""
    if open_files_limit == resource.RLIM_INFINITY:
        return max_connections
    return max(1, min(max_connections, open_files_limit // 2))


def accept_batch(cap: int) -> int:
    """Connections asyncio accepts in one go (its `backlog`): each holds a file before the protocol can
    close an idle one to make room, so a handful beside the cap."""
    return max(4, min(64, cap // 8))


class ConnectionGuard:
    """The sockets and connections of one server. Used on the event loop's thread only (the accept, the
    protocol callbacks, the transports' close), so it needs no lock."""

    def __init__(self, cap: int, request_head_timeout_s: float, clock=time.monotonic):
        self.cap = cap
        self.accept_limit = cap + max(accept_batch(cap), cap // 2)
        self.request_head_timeout_s = request_head_timeout_s
        self.clock = clock
        self.open: dict[GuardedH11Protocol, None] = {}  # connections that reached the protocol
        self.sockets: dict[int, tuple[_Accepted, float]] = {}  # file descriptor -> socket, accepted at (oldest first)
        self.with_protocol: set[int] = set()  # their descriptors
        self.shut: set[int] = set()  # stuck ones shut down, closed once asyncio sees it
        self._sweep = None  # the timer that ends handshakes that do not come (sweep_stuck)

    # --- the listening socket's side -------------------------------------------------------------------
    def accepted(self, sock: _Accepted, peer: str) -> bool:
        """Count `sock` in; False (it is to be closed) if it cannot be made room for."""
        now = self.clock()
        fd = sock.fileno()
        self.sockets[fd] = (sock, now)
        if self._sweep is None:
            self._sweep = asyncio.get_running_loop().call_later(self.request_head_timeout_s, self.sweep_stuck)
        if len(self.sockets) - len(self.shut) <= self.accept_limit:
            return True
        for other_fd, (other, at) in self.sockets.items():
            if other_fd not in self.with_protocol and other_fd not in self.shut and now - at >= STUCK_S:
                log.warning(
                    "connection %s closed to make room: open %.0f s without a request (a TLS handshake that "
                    "does not come?), %d sockets open",
                    _peer(other),
                    now - at,
                    len(self.sockets),
                )
                self._shut_down(other_fd, other)
                return True
        del self.sockets[fd]
        log.warning(
            "connection from %s refused: %d sockets open, none of them stuck to close (server.max_connections)",
            peer,
            self.accept_limit,
        )
        return False

    def sweep_stuck(self) -> None:
        """Shut down the sockets that have not reached the protocol within request_head_timeout_s (a TLS
        handshake that does not come: asyncio itself waits 60 s); again while any is left to watch."""
        self._sweep = None
        now = self.clock()
        for fd, (sock, at) in list(self.sockets.items()):
            if fd not in self.with_protocol and fd not in self.shut and now - at >= self.request_head_timeout_s:
                self._shut_down(fd, sock)
        if any(fd not in self.with_protocol and fd not in self.shut for fd in self.sockets):
            self._sweep = asyncio.get_running_loop().call_later(self.request_head_timeout_s / 2, self.sweep_stuck)

    def _shut_down(self, fd: int, sock: socket.socket) -> None:
        self.shut.add(fd)
        try:
            sock.shutdown(socket.SHUT_RDWR)  # asyncio reads the end and closes it (no fd pulled from under it)
        except OSError:
            pass

    def socket_closed(self, fd: int) -> None:
        self.sockets.pop(fd, None)
        self.with_protocol.discard(fd)
        self.shut.discard(fd)

    # --- the protocol's side ---------------------------------------------------------------------------
    def admit(self, protocol: GuardedH11Protocol) -> bool:
        """Room for `protocol`: a connection idle the longest is closed at the cap; False when every
        open connection is in a request."""
        sock = protocol.transport.get_extra_info("socket")
        if sock is not None:
            self.with_protocol.add(sock.fileno())
        if len(self.open) >= self.cap:
            idle = [p for p in self.open if p.waiting_for_request()]
            if not idle:
                return False
            victim = min(idle, key=lambda p: p.idle_since)
            log.warning(
                "connection from %s closed to make room: %d connections open, this one idle the longest "
                "(server.max_connections)",
                _client(victim),
                len(self.open),
            )
            victim.close_idle()  # its file is closed on the loop's next pass: counted out now
        self.open[protocol] = None
        return True

    def forget(self, protocol: GuardedH11Protocol) -> None:
        self.open.pop(protocol, None)


class _Accepted(socket.socket):
    """An accepted socket that tells the guard when it is closed (asyncio's transports close it)."""

    guard: ConnectionGuard

    def close(self) -> None:
        fd = self.fileno()
        if fd >= 0:
            self.guard.socket_closed(fd)
        super().close()


class _Listener(socket.socket):
    """The listening socket: its kernel queue stays KERNEL_BACKLOG long whatever backlog asyncio asks for
    (asyncio's backlog is also how many it accepts in one go, kept small: accept_batch); each socket it
    accepts is counted by the guard."""

    guard: ConnectionGuard

    def listen(self, backlog: int = KERNEL_BACKLOG) -> None:
        super().listen(max(backlog, KERNEL_BACKLOG))

    def accept(self) -> tuple[socket.socket, Any]:
        fd, address = self._accept()
        sock = _Accepted(self.family, self.type, self.proto, fileno=fd)
        sock.guard = self.guard
        if not self.guard.accepted(sock, _address(address)):
            sock.close()
            # asyncio's "nothing more to accept now": the next one is tried on the loop's next pass
            raise BlockingIOError("connection refused at the accept limit")
        return sock, address


def listening_sockets(host: str, port: int, guard: ConnectionGuard) -> list[socket.socket]:
    """Bound to every address of host:port as asyncio's create_server binds them (IPv6 ones IPv6 only), for
    `uvicorn.Server.run(sockets=...)`; an address or port that cannot be had is one line."""
    try:
        infos = socket.getaddrinfo(host.strip("[]"), port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError) as exc:
        raise StartError(f"cannot listen on {host}:{port}: the name does not resolve ({exc}); see --host") from None
    sockets: list[socket.socket] = []
    for family, kind, proto, _, address in dict.fromkeys(infos):
        sock = _Listener(family, kind, proto)
        sock.guard = guard
        sockets.append(sock)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if family == socket.AF_INET6:
            sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
        try:
            sock.bind(address)
        except OSError as exc:
            for opened in sockets:
                opened.close()
            raise StartError(
                f"cannot listen on {host}:{port}: {exc.strerror or exc} (another service on that port? --port, --host)"
            ) from None
    return sockets


def guarded_h11_protocol(guard: ConnectionGuard) -> type[H11Protocol]:
    """uvicorn's h11 protocol bounded by `guard` (pass the class as uvicorn.Config(http=...))."""

    class Guarded(GuardedH11Protocol):
        pass

    Guarded.guard = guard
    return Guarded


class GuardedH11Protocol(H11Protocol):
    guard: ConnectionGuard  # set on the subclass guarded_h11_protocol makes

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.idle_since = 0.0
        self._head_timer = None

    def connection_made(self, transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        if not self.guard.admit(self):
            log.warning(
                "connection from %s answered 503: all %d connections are in a request (server.max_connections)",
                _client(self),
                self.guard.cap,
            )
            transport.write(_BUSY)
            transport.close()
            return
        self._await_request_head()

    def connection_lost(self, exc: Exception | None) -> None:
        self.guard.forget(self)
        self._cancel_head_timer()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        cycle = self.cycle
        super().data_received(data)
        if self.cycle is not cycle:  # a whole request head arrived: the request's own time starts
            self._cancel_head_timer()

    def on_response_complete(self) -> None:
        cycle = self.cycle
        super().on_response_complete()  # may start a pipelined request at once
        if self.cycle is cycle and not self.transport.is_closing():
            self._await_request_head()

    def waiting_for_request(self) -> bool:
        return not self.transport.is_closing() and (self.cycle is None or self.cycle.response_complete)

    def close_idle(self) -> None:
        """Close a connection between requests (as uvicorn's keep-alive timeout does)."""
        self.guard.forget(self)
        self._cancel_head_timer()
        if not self.transport.is_closing():
            try:
                self.conn.send(h11.ConnectionClosed())
            except h11.LocalProtocolError:
                pass  # part-way through a request head: nothing of ours to end
            self.transport.close()

    def _await_request_head(self) -> None:
        self.idle_since = self.guard.clock()
        self._cancel_head_timer()
        self._head_timer = self.loop.call_later(self.guard.request_head_timeout_s, self._head_timed_out)

    def _head_timed_out(self) -> None:
        self._head_timer = None
        if self.waiting_for_request():
            self.close_idle()

    def _cancel_head_timer(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None


def _client(protocol: H11Protocol) -> str:
    return f"{protocol.client[0]}:{protocol.client[1]}" if protocol.client else "an unknown address"


def _address(address: Any) -> str:
    return f"{address[0]}:{address[1]}" if isinstance(address, tuple) and len(address) >= 2 else str(address)


def _peer(sock: socket.socket) -> str:
    try:
        return "from " + _address(sock.getpeername())
    except OSError:
        return "(its peer gone)"
