"""A CiA 402 device on a canopen LocalNode: state machine, statusword, NMT, consumer heartbeat.

The node is a real canopen LocalNode built from the same EDS the service reads (docs/interfaces.md,
"Object dictionaries"): client and server are tested against each other. The
state machine walks drivers.cia402.DEVICE_TRANSITIONS on every controlword (0x6040) write; the
statusword (0x6041), mode display (0x6061), error code (0x603F) and error register (0x1001) are
served live by a read callback. Subclasses add their objects with `read_object` / `write_object`.

Consumer heartbeat (0x1016:1 = node id << 16 | time in ms): after the first heartbeat of that node
was seen, silence longer than the time calls `heartbeat_lost()` once (then it must be seen again).
Time is wall-clock here: CAN is a real-time wire even when the plant runs faster.
"""

from __future__ import annotations

import logging
import threading
import time

import canopen
from canopen.sdo import SdoAbortedError

from drivers.cia402 import DEVICE_TRANSITIONS, State402, decode_controlword, encode_statusword

EMULATOR_STALL_GRACE_S = 0.2  # a watchdog this late means the emulator itself was starved
log = logging.getLogger(__name__)

ABORT_VALUE_RANGE = 0x06090030  # value range of parameter exceeded
ABORT_VALUE_TOO_HIGH = 0x06090031
ABORT_VALUE_TOO_LOW = 0x06090032
ABORT_NOT_IN_STATE = 0x08000022  # data cannot be transferred because of the present device state
NMT_RESET_COMMUNICATION = 0x82
NMT_ENTER_PRE_OPERATIONAL = 0x80
EMCY_HEARTBEAT = 0x8130  # life guard / heartbeat error
ERROR_REGISTER_COMM = 0x11  # generic + communication error


def encode(node: canopen.LocalNode, index: int, subindex: int, value) -> bytes:
    return node._find_object(index, subindex).encode_raw(value)


class Cia402Device:
    mode_of_operation = 0  # set by subclasses (4 profile torque, 3 profile velocity)

    def __init__(self, network: canopen.Network, node_id: int, eds_path: str):
        self.node = canopen.LocalNode(node_id, str(eds_path))
        self.network = network
        self.lock = threading.RLock()
        self.state = State402.SWITCH_ON_DISABLED  # transitions 0 and 1 happen at power-up
        self.error_code = 0
        self.power_off_at: float | None = None  # time.monotonic() when the power stage last went off
        self.node.add_read_callback(self._on_read)
        self.node.add_write_callback(self._on_write)
        network.add_node(self.node)
        hb = int(self.node.object_dictionary[0x1016][1].default)
        self._hb_node = 0
        self._hb_timeout_s = 0.0
        self._hb_last: float | None = None
        self._configure_heartbeat_consumer(hb)

    # -- lifecycle ---------------------------------------------------------------------------------
    def boot(self) -> None:
        """Boot-up message, then pre-operational with the producer heartbeat (0x1017)."""
        self.node.nmt.send_command(NMT_RESET_COMMUNICATION)
        self.node.nmt.send_command(NMT_ENTER_PRE_OPERATIONAL)

    def shutdown(self) -> None:
        self.node.nmt.stop_heartbeat()

    # -- object access hooks for subclasses ------------------------------------------------------
    def read_object(self, index: int, subindex: int):
        """Live value of an object, or None to serve the stored one."""
        return None

    def write_object(self, index: int, subindex: int, value) -> None:
        """Validate and act on a write; raise SdoAbortedError to refuse it (nothing is stored)."""

    def state_changed(self, old: State402, new: State402) -> None:
        """Called (with the lock held) after every state change."""

    def heartbeat_lost(self) -> None:
        """Safety reaction; default: FAULT."""
        self.fault(EMCY_HEARTBEAT)

    # -- state machine -----------------------------------------------------------------------------
    @property
    def power_on(self) -> bool:
        return self.state == State402.OPERATION_ENABLED

    def set_state(self, new: State402) -> None:
        with self.lock:
            old = self.state
            if new != old:
                self.state = new
                if old == State402.OPERATION_ENABLED:
                    self.power_off_at = time.monotonic()  # fault -> safe timing (faults.py status)
                log.info("node %d: %s -> %s", self.node.id, old.value, new.value)
                self.state_changed(old, new)

    def fault(self, error_code: int) -> None:
        with self.lock:
            self.error_code = error_code
            self.set_state(State402.FAULT)
        try:
            self.node.emcy.send(error_code, ERROR_REGISTER_COMM)
        except Exception:
            log.exception("node %d: EMCY send failed", self.node.id)

    def statusword(self) -> int:
        return encode_statusword(self.state)

    def store(self, index: int, subindex: int, value) -> None:
        """Change a stored OD value from inside the device (no write callbacks)."""
        self.node.data_store.setdefault(index, {})[subindex] = encode(self.node, index, subindex, value)

    def stored(self, index: int, subindex: int = 0):
        obj = self.node._find_object(index, subindex)
        try:
            raw = self.node.data_store[index][subindex]
        except KeyError:
            return obj.default
        return obj.decode_raw(raw)

    # -- canopen callbacks -------------------------------------------------------------------------
    def _on_read(self, index: int, subindex: int, od, **_):
        if index == 0x6041:
            return self.statusword()
        if index == 0x6061:
            return self.mode_of_operation
        if index == 0x603F:
            return self.error_code
        if index == 0x1001:
            return ERROR_REGISTER_COMM if self.state == State402.FAULT else 0
        return self.read_object(index, subindex)

    def _on_write(self, index: int, subindex: int, od, data: bytes, **_):
        value = od.decode_raw(data)
        with self.lock:
            if index == 0x6040:
                self._controlword(value)
            elif index == 0x6060:
                if value != self.mode_of_operation:
                    raise SdoAbortedError(ABORT_VALUE_RANGE)
            elif index == 0x1016 and subindex == 1:
                self._configure_heartbeat_consumer(value)
            else:
                self.write_object(index, subindex, value)

    def _controlword(self, controlword: int) -> None:
        command = decode_controlword(controlword)
        if command is None:
            return
        new = DEVICE_TRANSITIONS.get((self.state, command))
        if new is None:
            return
        if self.state == State402.FAULT and new != State402.FAULT:
            self.error_code = 0
            try:
                self.node.emcy.reset()
            except Exception:
                log.exception("node %d: EMCY reset failed", self.node.id)
        self.set_state(new)

    # -- consumer heartbeat ------------------------------------------------------------------------
    def _configure_heartbeat_consumer(self, value: int) -> None:
        node = (value >> 16) & 0x7F
        ms = value & 0xFFFF
        if self._hb_node:
            try:
                self.network.unsubscribe(0x700 + self._hb_node, self._on_heartbeat)
            except (KeyError, ValueError):
                pass
        self._hb_node = node
        self._hb_timeout_s = ms / 1000.0
        self._hb_last = None
        if node and ms:
            self.network.subscribe(0x700 + node, self._on_heartbeat)

    @property
    def heartbeat_consumer_ms(self) -> int:
        """The consumer heartbeat time in force (0x1016:1 low 16 bits; 0: not consuming)."""
        return int(round(self._hb_timeout_s * 1000)) if self._hb_node else 0

    def _on_heartbeat(self, can_id, data, timestamp) -> None:
        self._hb_last = time.monotonic()

    def check_heartbeat(self, now: float | None = None, emulator_stalled_s: float = 0.0) -> None:
        """Called periodically by the process: fires `heartbeat_lost` once per loss.

        `emulator_stalled_s`: how long the emulator's own watchdog was late. A real drive is never
        starved; the emulator on a loaded PC can be, and its receive thread with it, so a heartbeat
        that looks old after such a stall may just not have been read yet: the consumer re-arms
        instead of blaming the service (a service that is really silent is caught one timeout later)."""
        last = self._hb_last
        if last is None or self._hb_timeout_s <= 0:
            return
        now = time.monotonic() if now is None else now
        if emulator_stalled_s > EMULATOR_STALL_GRACE_S:
            log.warning(
                "node %d: emulator stalled %.2f s: heartbeat consumer re-armed", self.node.id, emulator_stalled_s
            )
            self._hb_last = now
            return
        if now - last > self._hb_timeout_s:
            self._hb_last = None
            log.warning("node %d: heartbeat of node %d lost", self.node.id, self._hb_node)
            with self.lock:
                self.heartbeat_lost()
