"""The emulator's CAN bus as an slcan adapter (the Lawicel ASCII protocol many USB-CAN adapters speak) on a loopback
TCP port, for python-can's own `slcan` interface: `can.Bus(interface="slcan", channel="socket://127.0.0.1:P")`
(pyserial's socket:// URL stands in for the adapter's serial port).

Every command and every frame is one line ending in CR (0x0D); the adapter answers a command with CR (done) or
BEL (0x07, refused):
    S0..S8     bitrate 10k..1M (S6 = 500 kbit/s)     -> CR (the emulated bus has no bit timing: taken as set)
    sXXYY      BTR0/BTR1 bit timing                  -> CR
    O / L      open (L: listen only: frames the client sends are refused)   -> CR; the bus's frames follow
    C          close                                  -> CR; no more frames
    V / v      hardware / software version            -> V1013 CR / v1013 CR
    N          serial number                          -> NRCAL CR
    F          status flags                           -> F00 CR
    tIIILDD..  standard frame (id 3 hex, dlc 1 digit, data 2 hex a byte) -> z CR, onto the bus
    TIIIIIIIILDD.. extended frame                     -> Z CR, onto the bus
    r / R      remote frames: refused (BEL): CANopen does not use them here
The bus's frames go to an open client as `tIIILDD..` / `TIIIIIIIILDD..` lines. A malformed line is refused with
BEL and logged; a line longer than MAX_LINE_CHARS is dropped.
"""

from __future__ import annotations

import logging
import socket

import can

from .can_bridge import BridgeClient, CanBridgeServer

log = logging.getLogger(__name__)

CR, BEL = "\r", "\a"
MAX_LINE_CHARS = 64  # the longest slcan line (an extended frame of 8 bytes) is 27 characters
BITRATES = {
    f"S{k}": rate
    for k, rate in enumerate((10_000, 20_000, 50_000, 100_000, 125_000, 250_000, 500_000, 800_000, 1_000_000))
}


def format_frame(msg: can.Message) -> str:
    """The slcan line of a data frame (without CR)."""
    data = bytes(msg.data).hex().upper()
    if msg.is_extended_id:
        return f"T{msg.arbitration_id & 0x1FFFFFFF:08X}{msg.dlc:d}{data}"
    return f"t{msg.arbitration_id & 0x7FF:03X}{msg.dlc:d}{data}"


def parse_frame(line: str) -> can.Message:
    """A data frame from its slcan line (`t...` or `T...`, without CR); ValueError saying what is wrong."""
    extended = line[0] == "T"
    id_chars = 8 if extended else 3
    if len(line) < 1 + id_chars + 1:
        raise ValueError(f"frame line too short: {line!r}")
    can_id = int(line[1 : 1 + id_chars], 16)
    if can_id > (0x1FFFFFFF if extended else 0x7FF):
        raise ValueError(f"CAN id out of range: {line[1 : 1 + id_chars]}")
    dlc = int(line[1 + id_chars])
    hex_data = line[2 + id_chars :]
    if not 0 <= dlc <= 8 or len(hex_data) != 2 * dlc:
        raise ValueError(f"dlc {dlc} does not match {len(hex_data) // 2} data bytes")
    return can.Message(arbitration_id=can_id, is_extended_id=extended, data=bytes.fromhex(hex_data), dlc=dlc)


class SlcanServer(CanBridgeServer):
    """slcan on host:port (port 0: a free one), bridged to virtual bus `bus_channel`."""

    log = log
    initial_state = "closed"

    def __init__(self, bus_channel: str, host: str = "127.0.0.1", port: int = 0):
        super().__init__("slcan-serve", bus_channel, host=host, port=port)

    @property
    def url(self) -> str:
        """The channel python-can's slcan interface opens (pyserial's socket URL)."""
        return f"socket://{self.host}:{self.port}"

    def format_frame(self, msg: can.Message) -> str:
        return format_frame(msg) + CR

    def on_readable(self, sock: socket.socket) -> None:
        client = self.received(sock)
        if client is None:
            return
        *lines, client.rx = client.rx.replace("\n", "").split(CR)
        if len(client.rx) > MAX_LINE_CHARS:
            log.warning("slcan: dropping over-long line %r...", client.rx[:40])
            client.rx = ""
        for line in lines:
            if len(line) > MAX_LINE_CHARS:
                log.warning("slcan: dropping over-long line %r...", line[:40])
                client.send_text(BEL)
                continue
            client.send_text(self._command(client, line))

    def _command(self, client: BridgeClient, line: str) -> str:
        """The adapter's answer to one line."""
        if not line:
            return CR  # an empty line: adapters answer CR (python-can sends none, terminals do)
        word = line[0]
        if line in BITRATES or (word == "s" and len(line) == 5):
            return CR
        if line in ("O", "L"):
            client.state = "open" if line == "O" else "listen"
            client.receiving = True
            return CR
        if line == "C":
            client.state, client.receiving = "closed", False
            return CR
        if line in ("V", "v"):
            return f"{line}1013{CR}"
        if line == "N":
            return f"NRCAL{CR}"
        if line == "F":
            return f"F00{CR}"
        if word in ("t", "T"):
            if client.state != "open":
                log.warning("slcan: %s sent a frame while %s, refused", client.addr, client.state)
                return BEL
            try:
                msg = parse_frame(line)
            except ValueError as exc:
                log.warning("slcan: malformed %r from %s: %s", line, client.addr, exc)
                return BEL
            self.from_client(client, msg)
            return ("z" if word == "t" else "Z") + CR
        log.warning("slcan: unsupported command %r from %s, refused", line[:40], client.addr)
        return BEL
