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

import logging
import socket
import time

import can

from .can_bridge import BridgeClient, CanBridgeServer

log = logging.getLogger(__name__)

MAX_LINE_CHARS = 512
RAW_GRACE_S = 0.2


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


class SocketcandServer(CanBridgeServer):
    """socketcand on host:port (port 0: pick a free one), bridged to virtual bus `bus_channel`."""

    log = log

    def __init__(self, bus_channel: str, host: str = "127.0.0.1", port: int = 0, channel: str = "can0"):
        self.channel = channel
        super().__init__("socketcand-serve", bus_channel, host=host, port=port)

    def format_frame(self, msg: can.Message) -> str:
        return format_frame(msg)

    def greeting(self, client: BridgeClient) -> None:
        client.send_text("< hi >")

    def on_readable(self, sock: socket.socket) -> None:
        client = self.received(sock)
        if client is None:
            return
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

    def _command(self, client: BridgeClient, body: str) -> None:
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
                client.receiving = True
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
            self.from_client(client, msg)
            return
        # in raw mode an '< error ... >' reply would be parsed as an error frame: just drop
        log.warning("socketcand: unsupported command %r from %s, ignored", body, client.addr)
