"""CiA 402 master logic shared by the drive and the load machine: SDO access, state machine, heartbeat.

Both devices are canopen RemoteNodes built from an EDS kept in the repo, accessed by SDO only
(expedited or segmented; never block transfer, which LocalNode-based peers do not support). Every SDO
failure becomes an SdoError naming the node, the object (index:sub and EDS name) and the abort code's
meaning, because "Code 0x06090030" alone does not tell an operator which setpoint was refused.

Enabling follows drivers.cia402.PATH_TO_OPERATION_ENABLED one command at a time and waits, with a
deadline, for the statusword to show each step; disabling is the safety path and tries every step even
when one fails (subclasses add their own "make it harmless first" steps, e.g. torque 0).
"""

from __future__ import annotations

import queue
import struct
import threading
import time
from pathlib import Path
from typing import Any, Callable

import canopen
from can import CanError
from canopen.emcy import EmcyError
from canopen.objectdictionary import ODVariable
from canopen.sdo import SdoAbortedError, SdoCommunicationError, SdoVariable

from drivers.canopen_bus import CanBus
from drivers.cia402 import (
    CONTROLWORD,
    PATH_TO_OPERATION_ENABLED,
    Command402,
    State402,
    decode_statusword,
)
from drivers.emcy_codes import describe_emcy
from drivers.errors import (
    DriveFaultError,
    FaultReactionActiveError,
    HeartbeatMissingError,
    NotConnectedError,
    SdoAbortError,
    SdoError,
    SdoTimeoutError,
    StateTransitionError,
    WrongDeviceError,
)

OD_CONTROLWORD = 0x6040
OD_STATUSWORD = 0x6041
OD_ERROR_CODE = 0x603F
OD_MODE_OF_OPERATION = 0x6060
OD_MODE_DISPLAY = 0x6061
OD_DEVICE_NAME = 0x1008
OD_DEVICE_TYPE = 0x1000  # CiA 301: device profile in the low word
OD_CONSUMER_HEARTBEAT = 0x1016
OD_PRODUCER_HEARTBEAT = 0x1017
OD_IDENTITY = 0x1018
SUB_VENDOR_ID = 1
SUB_PRODUCT_CODE = 2
IDENTITY_FIELDS = ((SUB_VENDOR_ID, "vendor id"), (SUB_PRODUCT_CODE, "product code"))

CONSUMER_HEARTBEAT_TIME_MS = 500
"""How long the device waits for the service heartbeat before it falls safe (0x1016:1, low 16 bits)."""

DEFAULT_PRODUCER_HEARTBEAT_MS = 100
"""Drive heartbeat period we configure if the device has its producer heartbeat (0x1017) switched off."""

HEARTBEAT_ALIVE_PERIODS = 3.0
"""The device counts as alive if its heartbeat was seen within this many of its periods ..."""

HEARTBEAT_ALIVE_MIN_S = 1.0
"""... and never less than this: a PC master's receive thread can be late by some 100 ms on a loaded
machine, and a drive whose link is really down falls safe on its own (it consumes our heartbeat),
so this check must not trip on scheduling jitter."""

FIRST_HEARTBEAT_WAIT_MIN_S = 3.0
"""connect() waits this long at least for the device's first heartbeat: it returns at the first one
heard, so the wait costs a healthy bench nothing, and a loaded start-up is not called a dead device."""

STATUS_POLL_INTERVAL_S = 0.002
"""Pause between statusword reads while waiting for a state change (each read is one SDO round trip)."""

FAULT_REACTION_WAIT_S = 10.0
"""fault_reset() waits this long for a fault reaction to end (a load machine braking from speed to
standstill takes seconds) before it says to try again."""

FAULT_REACTION_POLL_S = 0.05
"""Pause between statusword reads while a fault reaction runs."""

FAULT_REACTION_DOES = {"load machine": "still braking to standstill"}
"""What a device kind does during its fault reaction, for the message of a reset that came too early."""


class Cia402Master:
    """SDO access and CiA 402 state machine of one remote node.

    bus: a connected (or later connected) CanBus; node_id: the device's node id; eds_path: its EDS;
    mode_of_operation: the 0x6060 value enable() writes (4 profile torque, 3 profile velocity);
    sdo_timeout_s: how long one SDO request waits for its answer.
    """

    device_kind = "CiA 402 device"

    def __init__(self, bus: CanBus, node_id: int, eds_path: Path, mode_of_operation: int, sdo_timeout_s: float = 0.5):
        if not 1 <= node_id <= 127:
            raise ValueError(f"node_id must be 1..127, got {node_id}")
        if sdo_timeout_s <= 0:
            raise ValueError(f"sdo_timeout_s must be > 0, got {sdo_timeout_s}")
        self.bus = bus
        self.node_id = node_id
        self.mode_of_operation = mode_of_operation
        self.sdo_timeout_s = sdo_timeout_s
        self.eds_path = Path(eds_path)
        self.node = canopen.RemoteNode(node_id, str(eds_path))
        # per-instance override of the class default (0.3 s); one attempt, no silent retries
        self.node.sdo.RESPONSE_TIMEOUT = sdo_timeout_s
        self.node.sdo.MAX_RETRIES = 1
        # one SDO transfer at a time: the SDO client keeps a single response queue per node
        self._sdo_lock = threading.RLock()
        self._sdo_failed_at: float | None = None  # monotonic time of a transaction that lost its answer
        # called after every SDO transfer the device answered (an abort is an answer): a caller that watches
        # its own loop for silence (the bench watchdog) learns the loop is at work on a slow bus
        self.on_answer: Callable[[], None] | None = None
        self._network: canopen.Network | None = None
        self._heartbeat_lock = threading.Lock()
        self._heartbeat_seen_monotonic: float | None = None
        self._heartbeat_first_seen = threading.Event()
        self._heartbeat_nmt_state: int | None = None
        self.heartbeat_period_ms: int | None = None

    # -- lifecycle ----------------------------------------------------------------------------------
    def connect(self, arm_consumer: bool = True) -> None:
        """Attach the node to the bus's network, check that the node is the device the EDS describes
        (identity 0x1018, WrongDeviceError before anything is written), start heartbeat monitoring,
        set NMT OPERATIONAL and (arm_consumer) configure the device to consume the service heartbeat
        (so it falls safe if we die). arm_consumer=False leaves 0x1016 as found, for a caller that
        arms it (arm_heartbeat_consumer) only once it knows it stays."""
        network = self.bus.network
        if self._network is not None:
            return
        if self.node_id in network:
            raise RuntimeError(f"node {self.node_id} is already on this network (two clients for one node?)")
        network.add_node(self.node)
        # wall-clock arrival time of our own, independent of the transport's timestamp clock
        network.subscribe(0x700 + self.node_id, self._on_heartbeat)
        self._network = network
        try:
            self._check_identity()
            self.node.nmt.state = "OPERATIONAL"
            if arm_consumer:
                self.arm_heartbeat_consumer()
            period_ms = int(self.read(OD_PRODUCER_HEARTBEAT))
            if period_ms == 0:
                self.write(OD_PRODUCER_HEARTBEAT, 0, DEFAULT_PRODUCER_HEARTBEAT_MS)
                period_ms = DEFAULT_PRODUCER_HEARTBEAT_MS
            self.heartbeat_period_ms = period_ms
            self._wait_first_heartbeat()
            self._after_connect()
        except BaseException:
            self.close()
            raise

    def arm_heartbeat_consumer(self) -> None:
        """The device consumes the service heartbeat (0x1016:1 = service node << 16 | 500 ms): it falls
        safe (FAULT, EMCY 0x8130) when the heartbeat stops for longer."""
        self.write(OD_CONSUMER_HEARTBEAT, 1, (self.bus.service_node_id << 16) | CONSUMER_HEARTBEAT_TIME_MS)

    def heartbeat_consumer(self) -> int:
        """0x1016:1 as the device holds it (node << 16 | time in ms; 0: it consumes no heartbeat)."""
        return int(self.read(OD_CONSUMER_HEARTBEAT, 1))

    def set_heartbeat_consumer(self, value: int) -> None:
        """0x1016:1 written back as it was found (heartbeat_consumer())."""
        self.write(OD_CONSUMER_HEARTBEAT, 1, value)

    def disarm_heartbeat_consumer(self) -> None:
        """Orderly stop: tell the device to stop consuming the service heartbeat (0x1016:1 = 0), so that
        the service letting go of the bus is not a lost heartbeat (no FAULT, no reset needed at the next
        start). Call it after disable(); arm_heartbeat_consumer (or connect()) arms it again."""
        self.write(OD_CONSUMER_HEARTBEAT, 1, 0)

    def check_identity(self) -> str:
        """The node's identity against our EDS, as connect() checks it (WrongDeviceError naming what answered),
        and its device type (0x1000) too; a line saying what matched."""
        self._check_identity()
        entry = self.node.object_dictionary.get(OD_DEVICE_TYPE)
        want = None if entry is None or getattr(entry, "default", None) is None else int(entry.default)
        device_type = int(self.read(OD_DEVICE_TYPE))
        if want is not None and device_type != want:
            raise WrongDeviceError(
                f"node {self.node_id} is not the {self.device_kind}: its device type (0x1000) is 0x{device_type:08X}, "
                f"the {self.device_kind}'s EDS ({self.eds_path.name}) has 0x{want:08X}"
            )
        ids = ", ".join(
            f"{label} 0x{int(self.read(OD_IDENTITY, sub)):X}"
            for sub, label in IDENTITY_FIELDS
            if self._eds_default(OD_IDENTITY, sub) is not None
        )
        return f"device type 0x{device_type:08X}, {ids}, as {self.eds_path.name}"

    def _check_identity(self) -> None:
        """The node answers with the vendor id and product code (0x1018:1, :2) of our EDS, else
        WrongDeviceError naming what answered: node ids swapped, or another device at this id, would
        otherwise be commanded with the wrong object dictionary. A device without a product code
        (0x1018:2 is optional in CiA 301) is judged on its vendor id alone."""
        expected = {sub: self._eds_default(OD_IDENTITY, sub) for sub, _ in IDENTITY_FIELDS}
        found = {}
        for sub, want in expected.items():
            if want is None:
                continue
            try:
                found[sub] = int(self.read(OD_IDENTITY, sub))
            except SdoAbortError:
                if sub == SUB_VENDOR_ID:
                    raise  # mandatory in CiA 301: a node without it is no CANopen device we know
        if all(found[sub] == expected[sub] for sub in found):
            return
        name = self._device_name()
        answers = ", ".join(f"{label} 0x{found[sub]:X}" for sub, label in IDENTITY_FIELDS if sub in found)
        wants = ", ".join(f"{label} 0x{expected[sub]:X}" for sub, label in IDENTITY_FIELDS if expected[sub] is not None)
        raise WrongDeviceError(
            f"node {self.node_id} is not the {self.device_kind}: it answers as {answers}"
            + (f" ('{name}')" if name else "")
            + f", where the {self.device_kind} ({self.eds_path.name}) has {wants}"
        )

    def _eds_default(self, index: int, subindex: int) -> int | None:
        try:
            value = self.node.object_dictionary[index][subindex].default
        except KeyError:
            return None
        return None if value is None else int(value)

    def _device_name(self) -> str | None:
        """The node's own name (0x1008), for the message only: None when it has none to give."""
        try:
            return str(self.read(OD_DEVICE_NAME)).strip("\x00 ") or None
        except (SdoError, ValueError, UnicodeDecodeError):
            return None

    def _wait_first_heartbeat(self) -> None:
        # the heartbeat interlock trips on a device never heard; the bench is ready only once each was heard
        timeout_s = max(HEARTBEAT_ALIVE_PERIODS * self.heartbeat_period_ms / 1000.0, FIRST_HEARTBEAT_WAIT_MIN_S)
        if not self._heartbeat_first_seen.wait(timeout_s):
            raise HeartbeatMissingError(
                f"{self.device_kind} node {self.node_id}: answers SDO but sent no heartbeat "
                f"within {timeout_s:g} s (producer period 0x1017 = {self.heartbeat_period_ms} ms)"
            )

    def _after_connect(self) -> None:
        """Hook for subclasses: read constants the device reports (e.g. rated torque)."""

    def close(self) -> None:
        """Detach from the network (no SDO traffic; call disable() first to leave the device safe)."""
        network, self._network = self._network, None
        if network is None:
            return
        try:
            network.unsubscribe(0x700 + self.node_id, self._on_heartbeat)
        except (KeyError, ValueError):
            pass
        if network.nodes.get(self.node_id) is self.node:
            del network[self.node_id]

    @property
    def connected(self) -> bool:
        return self._network is not None and self.bus.connected

    def _require_connected(self) -> None:
        if not self.connected:
            raise NotConnectedError(f"{self.device_kind} node {self.node_id}: not connected (call connect() first)")

    # -- SDO access with clear errors ---------------------------------------------------------------
    def _object_name(self, index: int, subindex: int) -> str:
        od = self.node.object_dictionary
        try:
            entry = od[index]
            if isinstance(entry, ODVariable):
                return entry.name
            return f"{entry.name}.{entry[subindex].name}"
        except KeyError:
            return "<not in EDS>"

    def _variable(self, index: int, subindex: int):
        entry = self.node.sdo[index]
        if isinstance(entry, SdoVariable):
            return entry
        return entry[subindex]

    def _translate(self, action: str, index: int, subindex: int, exc: Exception, value: Any = None) -> SdoError:
        name = self._object_name(index, subindex)
        if isinstance(exc, SdoAbortedError):
            meaning = SdoAbortedError.CODES.get(exc.code, "unknown abort code")
            return SdoAbortError(
                self.node_id,
                action,
                index,
                subindex,
                name,
                f"aborted with 0x{exc.code:08X} ({meaning})",
                abort_code=exc.code,
                value=value,
            )
        if isinstance(exc, SdoCommunicationError) and "No SDO response" in str(exc):
            return SdoTimeoutError(
                self.node_id,
                action,
                index,
                subindex,
                name,
                f"no SDO response within {self.sdo_timeout_s:g} s (is node {self.node_id} on the bus and powered?)",
                value=value,
            )
        if isinstance(exc, CanError):
            return SdoError(self.node_id, action, index, subindex, name, f"CAN transport error: {exc}", value=value)
        return SdoError(self.node_id, action, index, subindex, name, f"{type(exc).__name__}: {exc}", value=value)

    def _quiet_channel(self) -> None:
        """After a transaction that failed without its answer (timeout, or an answer to another request),
        the device may still answer it late, and that answer would be taken for the next request's:
        wait out one more SDO timeout from the failure, dropping what arrives, before the next request.
        Called with the SDO lock held."""
        if self._sdo_failed_at is None:
            return
        deadline = self._sdo_failed_at + self.sdo_timeout_s
        self._sdo_failed_at = None
        while (left := deadline - time.monotonic()) > 0:
            try:
                self.node.sdo.responses.get(timeout=left)
            except queue.Empty:
                break
        self.node.sdo.responses = queue.Queue()

    def read(self, index: int, subindex: int = 0) -> Any:
        """Read one object by SDO (decoded per its EDS data type)."""
        self._require_connected()
        with self._sdo_lock:
            self._quiet_channel()
            try:
                value = self._variable(index, subindex).raw
            except SdoCommunicationError as exc:
                self._sdo_failed_at = time.monotonic()
                raise self._translate("read", index, subindex, exc) from exc
            except SdoAbortedError as exc:
                self._answered()
                raise self._translate("read", index, subindex, exc) from exc
            except CanError as exc:
                raise self._translate("read", index, subindex, exc) from exc
            self._answered()
            return value

    def write(self, index: int, subindex: int, value: Any) -> None:
        """Write one object by SDO (encoded per its EDS data type; expedited when it fits in 4 bytes)."""
        self._require_connected()
        with self._sdo_lock:
            self._quiet_channel()
            try:
                self._variable(index, subindex).raw = value
            except SdoCommunicationError as exc:
                self._sdo_failed_at = time.monotonic()
                raise self._translate("write", index, subindex, exc, value) from exc
            except SdoAbortedError as exc:
                self._answered()
                raise self._translate("write", index, subindex, exc, value) from exc
            except CanError as exc:
                raise self._translate("write", index, subindex, exc, value) from exc
            except (struct.error, TypeError, ValueError) as exc:
                name = self._object_name(index, subindex)
                raise ValueError(
                    f"node {self.node_id}: value {value!r} does not fit 0x{index:04X}:{subindex:02X} '{name}': {exc}"
                ) from exc
            self._answered()

    def download_domain(self, index: int, subindex: int, data: bytes) -> None:
        """Write a DOMAIN object by segmented SDO transfer (block transfer is never used)."""
        self._require_connected()
        with self._sdo_lock:
            self._quiet_channel()
            try:
                # segment by segment (the raw stream, unbuffered), so that each answered segment is reported
                with self.node.sdo.open(index, subindex, "wb", buffering=0, size=len(data), force_segment=True) as raw:
                    rest = memoryview(bytes(data))
                    while len(rest):
                        rest = rest[raw.write(rest) :]
                        self._answered()
            except SdoCommunicationError as exc:
                self._sdo_failed_at = time.monotonic()
                raise self._translate("write", index, subindex, exc, f"<{len(data)} bytes>") from exc
            except (SdoAbortedError, CanError) as exc:
                raise self._translate("write", index, subindex, exc, f"<{len(data)} bytes>") from exc
            self._answered()

    def _answered(self) -> None:
        if self.on_answer is not None:
            self.on_answer()

    # -- CiA 402 state machine ----------------------------------------------------------------------
    def statusword(self) -> int:
        return int(self.read(OD_STATUSWORD))

    def state(self) -> State402:
        """Current CiA 402 state, decoded from the statusword (one SDO read)."""
        return self._decode(self.statusword())

    def _decode(self, statusword: int) -> State402:
        try:
            return decode_statusword(statusword)
        except ValueError as exc:
            raise SdoError(
                self.node_id, "read", OD_STATUSWORD, 0, self._object_name(OD_STATUSWORD, 0), str(exc)
            ) from exc

    def send_command(self, command: Command402) -> None:
        """Write the controlword that carries one CiA 402 command."""
        self.write(OD_CONTROLWORD, 0, CONTROLWORD[command])

    def wait_for_state(
        self, accept: Callable[[State402], bool], deadline: float, what: str, last_command: Command402 | None = None
    ) -> State402:
        """Poll the statusword until accept(state) or the monotonic deadline passes."""
        while True:
            statusword = self.statusword()
            state = self._decode(statusword)
            if accept(state):
                return state
            if time.monotonic() >= deadline:
                sent = f" after {last_command.name}" if last_command is not None else ""
                raise StateTransitionError(
                    f"{self.device_kind} node {self.node_id}: {what} did not happen{sent}; "
                    f"still {state.name} (statusword 0x{statusword:04X}){self._fault_hint(state)}"
                )
            time.sleep(STATUS_POLL_INTERVAL_S)

    def _fault_hint(self, state: State402) -> str:
        if state not in (State402.FAULT, State402.FAULT_REACTION_ACTIVE):
            return ""
        code = self.error_code()
        return "" if code is None else f"; {describe_emcy(code)}"

    def error_code(self) -> int | None:
        """The device's error code (0x603F); None if it cannot be read."""
        try:
            return int(self.read(OD_ERROR_CODE))
        except SdoError:
            return None

    def fault_description(self) -> str:
        """'drive node 5 in FAULT: EMCY 0x3210 DC link over-voltage' (error code 0x603F)."""
        code = self.error_code()
        cause = describe_emcy(code) if code else "error code unknown"
        return f"{self.device_kind} node {self.node_id} in FAULT: {cause}"

    def enable(self, timeout_s: float = 2.0) -> None:
        """Set the mode of operation, then walk the CiA 402 state machine to OPERATION_ENABLED.

        One command per step, taken from PATH_TO_OPERATION_ENABLED for the state the device reports;
        after each command we wait for the state to change. A device in FAULT is never reset here:
        a fault is acknowledged by a person (fault_reset), so enable() raises DriveFaultError naming
        the error code. Raises StateTransitionError when timeout_s (for the whole walk) runs out.
        """
        self._require_connected()
        state = self.state()
        if state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE):
            raise DriveFaultError(self.fault_description() + "; acknowledge it with a fault reset first")
        self.write(OD_MODE_OF_OPERATION, 0, self.mode_of_operation)
        deadline = time.monotonic() + timeout_s
        while state is not State402.OPERATION_ENABLED:
            command = PATH_TO_OPERATION_ENABLED.get(state)
            if command is Command402.FAULT_RESET:
                raise DriveFaultError(self.fault_description() + " while enabling; acknowledge it with a fault reset")
            if command is None:
                # transient states (NOT_READY_TO_SWITCH_ON, FAULT_REACTION_ACTIVE) advance by themselves
                state = self.wait_for_state(
                    lambda s, prev=state: s is not prev, deadline, f"leaving {state.name} on its own"
                )
                continue
            self.send_command(command)
            state = self.wait_for_state(
                lambda s, prev=state: s is not prev,
                deadline,
                f"transition out of {state.name} towards OPERATION_ENABLED",
                command,
            )

    def fault_reset(self, timeout_s: float = 2.0, fault_reaction_timeout_s: float = FAULT_REACTION_WAIT_S) -> bool:
        """Acknowledge a FAULT: rising edge on controlword bit 7, wait (timeout_s) for it to leave FAULT.
        A device still in its fault reaction (FAULT_REACTION_ACTIVE: a load machine braking to
        standstill) cannot be reset yet: first wait up to fault_reaction_timeout_s for the reaction to
        end, else FaultReactionActiveError says what it waits for and to try again. Returns False if the
        device was not in FAULT (nothing sent). Only on a person's request (or an explicit auto-reset
        setting): the service never calls this on its own."""
        state = self.state()
        if state not in (State402.FAULT, State402.FAULT_REACTION_ACTIVE):
            return False
        if state is State402.FAULT_REACTION_ACTIVE:
            waited_from = time.monotonic()
            while state is State402.FAULT_REACTION_ACTIVE:
                if time.monotonic() - waited_from >= fault_reaction_timeout_s:
                    doing = FAULT_REACTION_DOES.get(self.device_kind, "still in its fault reaction")
                    raise FaultReactionActiveError(
                        f"{self.device_kind} node {self.node_id} is {doing} after its fault (FAULT_REACTION_ACTIVE, "
                        f"waited {time.monotonic() - waited_from:.0f} s)"
                        f"{self._fault_hint(State402.FAULT_REACTION_ACTIVE)}; try the reset again when it has stopped"
                    )
                time.sleep(FAULT_REACTION_POLL_S)  # seconds to wait: a statusword read per 50 ms will do
                state = self.state()
            if state is not State402.FAULT:
                return False  # the reaction ended elsewhere than in FAULT: nothing to acknowledge
        deadline = time.monotonic() + timeout_s
        # fault reset acts on the 0 -> 1 edge of bit 7
        self.send_command(Command402.DISABLE_VOLTAGE)
        self.send_command(Command402.FAULT_RESET)
        self.wait_for_state(lambda s: s is not State402.FAULT, deadline, "fault reset", Command402.FAULT_RESET)
        return True

    def add_emcy_callback(self, callback: Callable[[EmcyError], None]) -> None:
        """Call `callback(EmcyError)` from the CAN receive thread for every EMCY of this node."""
        self.node.emcy.add_callback(callback)

    def _safe_steps(self) -> list[tuple[str, Callable[[], None]]]:
        """Steps that make the device harmless before its power stage goes off (subclasses add)."""
        return []

    def disable(self, timeout_s: float = 2.0) -> None:
        """Safety path: make the device harmless, then DISABLE_VOLTAGE and wait for SWITCH_ON_DISABLED.

        Every step is tried even if an earlier one failed (a lost SDO must not keep the power stage
        on); the first error is raised after all steps ran.
        """
        errors: list[BaseException] = []
        steps = self._safe_steps() + [
            ("disable voltage", lambda: self.send_command(Command402.DISABLE_VOLTAGE)),
            (
                "wait for SWITCH_ON_DISABLED",
                lambda: self.wait_for_state(
                    lambda s: s in (State402.SWITCH_ON_DISABLED, State402.FAULT),
                    time.monotonic() + timeout_s,
                    "switching off",
                    Command402.DISABLE_VOLTAGE,
                ),
            ),
        ]
        for _name, step in steps:
            try:
                step()
            except Exception as exc:  # noqa: BLE001 - keep going, report the first one
                errors.append(exc)
        if errors:
            raise errors[0]

    # -- heartbeat and EMCY -------------------------------------------------------------------------
    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._heartbeat_lock:
            self._heartbeat_seen_monotonic = time.monotonic()
            self._heartbeat_nmt_state = data[0] & 0x7F if data else None
        self._heartbeat_first_seen.set()

    def heartbeat_age_s(self) -> float | None:
        """Seconds since the device's last heartbeat (None: never seen)."""
        with self._heartbeat_lock:
            seen = self._heartbeat_seen_monotonic
        return None if seen is None else time.monotonic() - seen

    def heartbeat_alive(self) -> bool:
        """True if the device's heartbeat was seen within 3 of its periods (0x1017, read at connect),
        and at least HEARTBEAT_ALIVE_MIN_S."""
        age = self.heartbeat_age_s()
        if age is None or not self.heartbeat_period_ms:
            return False
        return age <= max(HEARTBEAT_ALIVE_PERIODS * self.heartbeat_period_ms / 1000.0, HEARTBEAT_ALIVE_MIN_S)

    @property
    def nmt_state(self) -> int | None:
        """NMT state byte of the last heartbeat (5 operational, 127 pre-operational, 4 stopped)."""
        with self._heartbeat_lock:
            return self._heartbeat_nmt_state

    @property
    def emcy_log(self) -> list[EmcyError]:
        """EMCY messages received from the device since the node was created (oldest first)."""
        return list(self.node.emcy.log)

    @property
    def emcy_active(self) -> list[EmcyError]:
        """EMCY errors not yet cleared by an error-reset EMCY."""
        return list(self.node.emcy.active)
