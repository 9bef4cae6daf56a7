"""A socketcand server (raw mode) on loopback, bridged to a python-can virtual bus.

Protocol as spoken by python-can's socketcand client (can/interfaces/socketcand/socketcand.py) and
socketcand itself:

    server: < hi >
    client: < open can0 >        server: < ok >
    client: < rawmode >          server: < ok >
    client: < send 705 8 1 2 3 4 5 6 7 8 >          (id hex, dlc hex, bytes as separate hex)
    server: < frame 705 1700000000.000000 0102030405060708 >   (data as ONE contiguous hex string)

The client compares each handshake reply with a single recv, so every reply goes out as its own
send, and no frame is sent to a client until a short grace period after its `rawmode` reply (frames
meanwhile are queued, not lost). Frames from one client go to the internal virtual bus (where the
emulator's canopen Network listens) and to every other client; frames the emulator sends on the
virtual bus go to all clients. Malformed lines are logged and dropped; a client that disconnects or
stops reading is dropped, never the server.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import socket
import threading
import time

import can

from .tcp_server import TcpServer

log = logging.getLogger(__name__)

MAX_LINE_CHARS = 512
RAW_GRACE_S = 0.2


class _Client:
    def __init__(self, sock: socket.socket, addr):
        self.sock = sock
        self.addr = addr
        self.rx = ""
        self.state = "hello"  # hello -> open -> raw
        self.ready_at = 0.0
        self.queued: list[str] = []
        self.lock = threading.Lock()
        self.dead = False

    def send_text(self, text: str) -> None:
        with self.lock:
            self._send_locked(text)

    def deliver(self, text: str | None, now: float) -> None:
        """Send a frame line, or queue it while the handshake grace period runs."""
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
            log.info("socketcand client %s: send failed (%s), dropping", self.addr, exc)
            self.dead = True


def format_frame(msg: can.Message) -> str:
    """`< frame ID SECONDS.USECS DATA >` with DATA one contiguous hex string (as socketcand
    sends it: module doc)."""
    if msg.is_extended_id:
        can_id = f"{msg.arbitration_id & 0x1FFFFFFF:08X}"
    else:
        can_id = f"{msg.arbitration_id & 0x7FF:03X}"
    ts = msg.timestamp if msg.timestamp else time.time()
    return f"< frame {can_id} {ts:.6f} {bytes(msg.data).hex().upper()} >"


def parse_send(body: str) -> can.Message:
    """Message from the body of `< send ID DLC B0 B1 ... >` (without the brackets). ValueError if bad."""
    parts = body.split()
    if len(parts) < 3 or parts[0] != "send":
        raise ValueError(f"not a send command: {body!r}")
    id_text = parts[1]
    can_id = int(id_text, 16)
    extended = len(id_text) > 3
    if can_id < 0 or can_id > (0x1FFFFFFF if extended else 0x7FF):
        raise ValueError(f"CAN id out of range: {id_text}")
    dlc = int(parts[2], 16)
    data = bytes(int(b, 16) for b in parts[3:])
    if not 0 <= dlc <= 8 or len(data) != dlc:
        raise ValueError(f"dlc {dlc} does not match {len(data)} data bytes")
    return can.Message(arbitration_id=can_id, is_extended_id=extended, data=data, dlc=dlc)


class SocketcandServer(TcpServer):
    """socketcand on host:port (port 0: pick a free one), bridged to virtual bus `bus_channel`."""

    log = log

    def __init__(self, bus_channel: str, host: str = "127.0.0.1", port: int = 0, channel: str = "can0"):
        self.channel = channel
        self.bus = can.Bus(interface="virtual", channel=bus_channel, receive_own_messages=False)
        super().__init__("socketcand-serve", host=host, port=port, backlog=8)
        # fault hook: can_id -> seconds to hold a frame the emulator sends (0: none); held frames keep
        # their order among themselves
        self.delay_for = None
        self._held: list[tuple[float, int, can.Message]] = []
        self._held_seq = itertools.count()
        self._threads.append(threading.Thread(target=self._pump, name="socketcand-pump", daemon=True))

    # -- lifecycle ---------------------------------------------------------------------------------
    def close(self) -> None:
        super().close()
        self.bus.shutdown()

    @property
    def client_count(self) -> int:
        with self._clients_lock:
            return len(self._clients)

    # -- selector thread (TcpServer hooks) ---------------------------------------------------------
    def on_accept(self, sock: socket.socket, addr) -> _Client:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        client = _Client(sock, addr)
        log.info("socketcand: client %s connected", addr)
        client.send_text("< hi >")
        return client

    def on_readable(self, sock: socket.socket) -> None:
        client = self._clients.get(sock)
        if client is None:
            return
        data = self.recv(sock)
        if data is None:
            return
        client.rx += data.decode("ascii", errors="replace")
        while True:
            start = client.rx.find("<")
            if start < 0:
                if client.rx.strip():
                    log.warning("socketcand: dropping garbage %r", client.rx[:80])
                client.rx = ""
                break
            end = client.rx.find(">", start)
            if end < 0:
                if len(client.rx) - start > MAX_LINE_CHARS:
                    log.warning("socketcand: dropping over-long command %r...", client.rx[start : start + 80])
                    client.rx = ""
                else:
                    client.rx = client.rx[start:]
                break
            if client.rx[:start].strip():
                log.warning("socketcand: dropping garbage %r", client.rx[:start][:80])
            body = client.rx[start + 1 : end].strip()
            client.rx = client.rx[end + 1 :]
            self._command(client, body)

    def client_closed(self, sock: socket.socket) -> None:
        client = self._clients.get(sock)
        if client is not None:
            log.info("socketcand: client %s disconnected", client.addr)
        super().client_closed(sock)

    def after_events(self) -> None:
        self._reap()

    def on_drop(self, sock: socket.socket, client: _Client | None) -> None:
        if client is not None:
            client.dead = True

    def _command(self, client: _Client, body: str) -> None:
        word = body.split(" ", 1)[0] if body else ""
        if client.state == "hello":
            if word == "open":
                requested = body[4:].strip()
                if requested == self.channel:
                    client.state = "open"
                    client.send_text("< ok >")
                else:
                    client.send_text("< error could not open bus >")
            else:
                log.warning("socketcand: %s sent %r before open, ignored", client.addr, body)
            return
        if word == "rawmode":
            with client.lock:
                client.ready_at = time.monotonic() + RAW_GRACE_S
                client.state = "raw"
                client._send_locked("< ok >")
            return
        if word == "echo":
            client.send_text("< echo >")
            return
        if word == "send":
            if client.state != "raw":
                log.warning("socketcand: %s sent a frame outside raw mode, ignored", client.addr)
                return
            try:
                msg = parse_send(body)
            except ValueError as exc:
                log.warning("socketcand: malformed %r from %s: %s", body, client.addr, exc)
                return
            msg.timestamp = time.time()
            self.bus.send(msg)
            self._broadcast(format_frame(msg), exclude=client)
            return
        # in raw mode an '< error ... >' reply would be parsed as an error frame: just drop
        log.warning("socketcand: unsupported command %r from %s, ignored", body, client.addr)

    def _pump(self) -> None:
        """Virtual bus -> all raw-mode clients; also releases frames queued during the grace period."""
        while not self._stop.is_set():
            now = time.monotonic()
            while self._held and self._held[0][0] <= now:
                self._broadcast(format_frame(heapq.heappop(self._held)[2]))
            timeout = 0.05 if not self._held else max(0.0, min(0.05, self._held[0][0] - now))
            try:
                msg = self.bus.recv(timeout=timeout)
            except Exception:
                if self._stop.is_set():
                    break
                log.exception("socketcand: virtual bus receive failed")
                continue
            if msg is not None and not msg.is_error_frame and not msg.is_remote_frame:
                delay = self.delay_for(msg.arbitration_id) if self.delay_for is not None else 0.0
                if delay > 0.0:
                    heapq.heappush(self._held, (time.monotonic() + delay, next(self._held_seq), msg))
                else:
                    self._broadcast(format_frame(msg))
            else:
                self._broadcast(None)

    def _broadcast(self, text: str | None, exclude: _Client | None = None) -> None:
        now = time.monotonic()
        with self._clients_lock:
            clients = [c for c in self._clients.values() if c.state == "raw" and c is not exclude]
        for c in clients:
            c.deliver(text, now)

    def _reap(self) -> None:
        with self._clients_lock:
            dead = [s for s, c in self._clients.items() if c.dead]
        for s in dead:
            self.drop(s)
