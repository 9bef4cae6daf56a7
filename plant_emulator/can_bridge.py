"""The emulator's CAN bus offered on a loopback TCP port: the part every wire protocol shares.

A `CanBridgeServer` joins the internal python-can virtual bus (where the emulator's canopen Network listens) and
serves TCP clients: frames a client sends go to the virtual bus and to every other client; frames on the virtual
bus go to every client that is receiving. A subclass speaks its protocol: it parses the client's bytes
(`on_readable`), says when a client receives (`BridgeClient.receiving`) and writes a frame as its text (`format_frame`).
A client that disconnects or stops reading is dropped, never the server. The fault hook `delay_for(can_id)` holds
frames the emulator sends (SDO answers) for that long, in order.

Protocols: socketcand (socketcand_server.py, python-can's `socketcand` interface) and slcan (slcan_server.py,
python-can's `slcan` interface over `socket://`).
"""

from __future__ import annotations

import heapq
import itertools
import logging
import socket
import threading
import time
from typing import cast

import can

from .tcp_server import TcpServer

log = logging.getLogger(__name__)


class BridgeClient:
    """A connected client: its receive buffer, its protocol state, and frames queued while it may not yet take them."""

    def __init__(self, sock: socket.socket, addr, state: str):
        self.sock = sock
        self.addr = addr
        self.rx = ""
        self.state = state
        self.receiving = False  # frames of the bus go to it (after its protocol's open)
        self.ready_at = 0.0  # frames are queued, not sent, until then (a handshake's grace period)
        self.queued: list[str] = []
        self.lock = threading.Lock()
        self.dead = False

    def send_text(self, text: str) -> None:
        with self.lock:
            self._send_locked(text)

    def deliver(self, text: str | None, now: float) -> None:
        """Send a frame's text, or queue it while the client's grace period runs."""
        with self.lock:
            if self.dead:
                return
            if now < self.ready_at:
                if text is not None:
                    self.queued.append(text)
                return
            out = "".join(self.queued) + (text or "")
            self.queued.clear()
            if out:
                self._send_locked(out)

    def _send_locked(self, text: str) -> None:
        if self.dead:
            return
        try:
            self.sock.sendall(text.encode("ascii"))
        except OSError as exc:
            log.info("CAN bridge client %s: send failed (%s), dropping", self.addr, exc)
            self.dead = True


class CanBridgeServer(TcpServer):
    """The virtual bus `bus_channel` on host:port (port 0: a free one); subclasses speak the protocol."""

    initial_state = "hello"

    def __init__(self, name: str, bus_channel: str, host: str = "127.0.0.1", port: int = 0):
        self.bus = can.Bus(interface="virtual", channel=bus_channel, receive_own_messages=False)
        super().__init__(name, host=host, port=port, backlog=8)
        # fault hook: can_id -> seconds to hold a frame the emulator sends (0: none); held frames keep
        # their order among themselves
        self.delay_for = None
        self._held: list[tuple[float, int, can.Message]] = []
        self._held_seq = itertools.count()
        self._threads.append(threading.Thread(target=self._pump, name=f"{name}-pump", daemon=True))

    def format_frame(self, msg: can.Message) -> str:
        raise NotImplementedError

    def greeting(self, client: BridgeClient) -> None:
        """What a new client is sent first (nothing unless the protocol has a greeting)."""

    # -- lifecycle ---------------------------------------------------------------------------------
    def close(self) -> None:
        super().close()
        self.bus.shutdown()

    def client_of(self, sock: socket.socket) -> BridgeClient | None:
        """The client on `sock` (TcpServer keeps every client's state as this server's on_accept made it)."""
        return cast(BridgeClient | None, self._clients.get(sock))

    def received(self, sock: socket.socket) -> BridgeClient | None:
        """The client on `sock` with what it sent appended to its `rx` (ASCII: both protocols are text); None when
        there is no client or nothing came (a closed connection is handled by TcpServer.recv)."""
        client = self.client_of(sock)
        if client is None:
            return None
        data = self.recv(sock)
        if data is None:
            return None
        client.rx += data.decode("ascii", errors="replace")
        return client

    def _all_clients(self) -> dict[socket.socket, BridgeClient]:
        with self._clients_lock:
            return cast(dict[socket.socket, BridgeClient], dict(self._clients))

    @property
    def client_count(self) -> int:
        with self._clients_lock:
            return len(self._clients)

    # -- selector thread (TcpServer hooks) ---------------------------------------------------------
    def on_accept(self, sock: socket.socket, addr) -> BridgeClient:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        client = BridgeClient(sock, addr, self.initial_state)
        self.log.info("%s: client %s connected", self.name, addr)
        self.greeting(client)
        return client

    def client_closed(self, sock: socket.socket) -> None:
        client = self.client_of(sock)
        if client is not None:
            self.log.info("%s: client %s disconnected", self.name, client.addr)
        super().client_closed(sock)

    def after_events(self) -> None:
        self._reap()

    def on_drop(self, sock: socket.socket, client: BridgeClient | None) -> None:
        if client is not None:
            client.dead = True

    def from_client(self, client: BridgeClient, msg: can.Message) -> None:
        """A frame a client sent: onto the virtual bus and to every other receiving client."""
        msg.timestamp = time.time()
        self.bus.send(msg)
        self._broadcast(self.format_frame(msg), exclude=client)

    # -- the pump ----------------------------------------------------------------------------------
    def _pump(self) -> None:
        """Virtual bus -> every receiving client; also releases frames queued during a grace period."""
        while not self._stop.is_set():
            now = time.monotonic()
            while self._held and self._held[0][0] <= now:
                self._broadcast(self.format_frame(heapq.heappop(self._held)[2]))
            timeout = 0.05 if not self._held else max(0.0, min(0.05, self._held[0][0] - now))
            try:
                msg = self.bus.recv(timeout=timeout)
            except Exception:
                if self._stop.is_set():
                    break
                self.log.exception("%s: virtual bus receive failed", self.name)
                continue
            if msg is not None and not msg.is_error_frame and not msg.is_remote_frame:
                delay = self.delay_for(msg.arbitration_id) if self.delay_for is not None else 0.0
                if delay > 0.0:
                    heapq.heappush(self._held, (time.monotonic() + delay, next(self._held_seq), msg))
                else:
                    self._broadcast(self.format_frame(msg))
            else:
                self._broadcast(None)

    def _broadcast(self, text: str | None, exclude: BridgeClient | None = None) -> None:
        now = time.monotonic()
        clients = [c for c in self._all_clients().values() if c.receiving and c is not exclude]
        for c in clients:
            c.deliver(text, now)

    def _reap(self) -> None:
        dead = [s for s, c in self._all_clients().items() if c.dead]
        for s in dead:
            self.drop(s)
