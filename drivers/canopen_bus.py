"""One CAN bus with a canopen Network on it, and the service's own NMT heartbeat.

The transport is chosen by the python-can interface string alone (socketcand, socketcan, pcan, kvaser,
virtual, ...): the same code talks to the emulator and to a real bench. The heartbeat matters for
safety: the drive consumes it (0x1016) and drops to torque 0 when the service goes silent, so it stops
when the service lets go of the bus. A device may consume it from power-up (0x1016 stored armed):
such a device starts watching at the first heartbeat it hears, and faults when it stops. So a master
that may still give up (a bench not yet complete) connects without it (`connect(heartbeat=False)`)
and starts it (`start_heartbeat()`) once it stays: a bus let go of before then faults nothing.

One master per node id: a second master on the bus with our node id (another `ripplecal serve`, a
CLI run with --bench) would command the same drives, and a drive would take its heartbeat for ours.
Transports do not hand a bus its own frames back (python-can's `receive_own_messages` is off by
default; the emulator's socketcand server sends a client's frames to the other clients only), so a
heartbeat heard on our own COB-ID (0x700 + service_node_id) comes from another node using our id.
`connect()` listens before it produces its heartbeat and refuses (ForeignMasterError) when one is
heard; a connected bus keeps listening and `foreign_master()` names what it heard.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import can
import canopen

from drivers.errors import ForeignMasterError, NotConnectedError

NMT_STATE_OPERATIONAL = 0x05
HEARTBEAT_COB_BASE = 0x700

NOTIFIER_CYCLE_S = 0.1
"""Receive-thread wake-up period: disconnect() waits for it, and the safety path must not hang ~1 s
(canopen's default) before the bus is really released."""

FOREIGN_LISTEN_PERIODS = 2.0
"""connect() listens for another master's heartbeat for this many of our heartbeat periods (another
ripplecal sends at the same period) after the first frame it hears (the receive path is live then:
socketcand holds a new client's frames back for its handshake) ..."""

FOREIGN_LISTEN_MIN_S = 0.2
"""... and at least this long, for a loaded PC's receive thread ..."""

FOREIGN_LISTEN_MAX_S = 0.5
"""... and no longer than this in all (a silent bus: nothing to hear; a master with a period up to
some 0.2 s is heard within it even behind socketcand's 0.2 s handshake hold)."""

FOREIGN_MASTER_HOLD_S = 2.0
"""foreign_master() reports another master for this long after its last heartbeat was heard."""


# python-can keyword arguments that suit a transport unless the settings say otherwise (can.options):
# socketcand carries every frame as text over TCP; without tcp_tune (TCP_NODELAY and TCP_QUICKACK)
# Nagle's algorithm and delayed ACKs hold an SDO answer back by ~40 ms now and then
INTERFACE_DEFAULTS: dict[str, dict[str, Any]] = {"socketcand": {"tcp_tune": True}}


class _OwnIdWatch(can.Listener):
    """Every frame's arrival (is the receive path live?) and heartbeats on our own COB-ID, which only
    another node using our id sends (receive thread)."""

    def __init__(self, cob_id: int):
        self.cob_id = cob_id
        self.lock = threading.Lock()
        self.first_frame_at: float | None = None
        self.heard = threading.Event()  # a foreign heartbeat was heard (connect's listening ends)
        self.foreign_count = 0
        self.foreign_last_at: float | None = None

    def on_message_received(self, msg: can.Message) -> None:
        now = time.monotonic()
        own_echo = getattr(msg, "is_rx", True) is False  # a transport set to hand our frames back
        foreign = (
            msg.arbitration_id == self.cob_id
            and not msg.is_extended_id
            and not msg.is_remote_frame
            and not msg.is_error_frame
            and not own_echo
        )
        with self.lock:
            if self.first_frame_at is None:
                self.first_frame_at = now
            if foreign:
                self.foreign_count += 1
                self.foreign_last_at = now
        if foreign:
            self.heard.set()

    def snapshot(self) -> tuple[float | None, int, float | None]:
        with self.lock:
            return self.first_frame_at, self.foreign_count, self.foreign_last_at


class CanBus:
    """A python-can bus, a canopen.Network on it, and the periodic service heartbeat.

    interface, channel, host, port, bitrate: passed to `can.Bus` (only those that are set), so every
    python-can transport works unchanged. service_node_id: our node id on the bus; the heartbeat goes
    out on COB-ID 0x700 + service_node_id with one byte 0x05 (operational) every heartbeat_period_ms.
    Another master heard on that COB-ID: connect() refuses (ForeignMasterError), foreign_master()
    names it while connected (a transport told to hand our own frames back, `receive_own_messages`,
    would hear itself: the check is off then).
    """

    def __init__(
        self,
        interface: str,
        channel: str | int,
        host: str | None = None,
        port: int | None = None,
        bitrate: int | None = None,
        service_node_id: int = 1,
        heartbeat_period_ms: int = 100,
        **bus_kwargs: Any,
    ):
        if not 1 <= service_node_id <= 127:
            raise ValueError(f"service_node_id must be 1..127, got {service_node_id}")
        if heartbeat_period_ms <= 0:
            raise ValueError(f"heartbeat_period_ms must be > 0, got {heartbeat_period_ms}")
        self.interface = interface
        self.channel = channel
        self.host = host
        self.port = port
        self.bitrate = bitrate
        self.service_node_id = service_node_id
        self.heartbeat_period_ms = heartbeat_period_ms
        self._extra_bus_kwargs = bus_kwargs
        self._network: canopen.Network | None = None
        self._heartbeat_task = None
        self._watch: _OwnIdWatch | None = None
        self._lock = threading.Lock()

    # -- lifecycle ----------------------------------------------------------------------------------
    def bus_kwargs(self) -> dict[str, Any]:
        """Arguments for can.Bus: the interface string decides the transport; unset options are left out
        so that each interface applies its own defaults (virtual has no host, socketcan no bitrate)."""
        kwargs: dict[str, Any] = {
            "interface": self.interface,
            "channel": self.channel,
            **INTERFACE_DEFAULTS.get(self.interface, {}),
        }
        for key in ("host", "port", "bitrate"):
            value = getattr(self, key)
            if value is not None and value != "":  # "" in a bench file: not set (TOML has no null)
                kwargs[key] = value
        kwargs.update(self._extra_bus_kwargs)
        return kwargs

    def connect(self, heartbeat: bool = True) -> "CanBus":
        """Open the bus, start the canopen notifier, listen for another master using our node id (up
        to FOREIGN_LISTEN_MAX_S, usually a few tenths of a second), then start the service heartbeat
        (heartbeat=False: not yet, see start_heartbeat). Raises ForeignMasterError (the bus closed
        again, nothing sent) when one is heard. Idempotent."""
        with self._lock:
            if self._network is not None:
                return self
            bus = can.Bus(**self.bus_kwargs())
            network = canopen.Network(bus)
            network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
            # python-can's software periodic task serialises its sends with this per-bus lock (created
            # lazily if absent); sharing canopen's send lock keeps heartbeat and SDO frames from being
            # sent by two threads at once on transports that are not thread-safe (socketcand's TCP text)
            if not hasattr(bus, "_lock_send_periodic"):
                bus._lock_send_periodic = network.send_lock
            watch = None if self._hears_itself() else _OwnIdWatch(self.heartbeat_cob_id)
            if watch is not None:
                network.listeners.append(watch)  # the notifier network.connect() starts calls it
            try:
                network.connect()
                if watch is not None:
                    # before our own heartbeat goes out: a second one with this id would keep the other
                    # master's drive alive on our account
                    self._listen_for_foreign_master(watch)
                if heartbeat:
                    self._heartbeat_task = self._send_heartbeat(network)
            except BaseException:
                network.disconnect()
                raise
            self._network = network
            self._watch = watch
            return self

    def start_heartbeat(self) -> None:
        """Start producing the service heartbeat on a bus connected without it (connect(heartbeat=False));
        from now on a device that consumes it faults when it stops. Idempotent."""
        with self._lock:
            if self._network is None:
                raise NotConnectedError(f"CAN bus {self._where()} is not connected (call CanBus.connect() first)")
            if self._heartbeat_task is None:
                self._heartbeat_task = self._send_heartbeat(self._network)

    def _send_heartbeat(self, network: canopen.Network):
        return network.send_periodic(
            self.heartbeat_cob_id, bytes([NMT_STATE_OPERATIONAL]), self.heartbeat_period_ms / 1000.0
        )

    def _hears_itself(self) -> bool:
        return bool(self._extra_bus_kwargs.get("receive_own_messages"))

    def _listen_for_foreign_master(self, watch: _OwnIdWatch) -> None:
        started = time.monotonic()
        listen_s = max(FOREIGN_LISTEN_PERIODS * self.heartbeat_period_ms / 1000.0, FOREIGN_LISTEN_MIN_S)
        while True:
            first_frame_at = watch.snapshot()[0]
            end = started + FOREIGN_LISTEN_MAX_S
            if first_frame_at is not None:
                end = min(end, max(first_frame_at, started) + listen_s)
            left = end - time.monotonic()
            if watch.heard.wait(max(0.0, min(left, 0.02))):
                raise ForeignMasterError(
                    f"CAN bus {self._where()}: {self._describe_foreign(watch)}; two masters with one node id "
                    f"would both command the bench's devices, which would take the other's heartbeat for ours "
                    f"(is another ripplecal serve, or a CLI run with --bench, on this bench?); not connected"
                )
            if left <= 0:
                return

    def _describe_foreign(self, watch: _OwnIdWatch) -> str:
        _, count, last_at = watch.snapshot()
        age = "" if last_at is None else f" ({count} heard, the last {time.monotonic() - last_at:.1f} s ago)"
        return f"another master sends heartbeats as node {self.service_node_id} on {self.channel}{age}"

    def foreign_master(self) -> str | None:
        """None, or what was heard while connected: "another master sends heartbeats as node 1 on can0
        (12 heard, the last 0.1 s ago)", while its last heartbeat is at most FOREIGN_MASTER_HOLD_S old.
        Cheap (no bus traffic): the service's interlocks may poll it."""
        watch = self._watch
        if watch is None or self._network is None:
            return None
        last_at = watch.snapshot()[2]
        if last_at is None or time.monotonic() - last_at > FOREIGN_MASTER_HOLD_S:
            return None
        return self._describe_foreign(watch)

    def _where(self) -> str:
        where = f"{self.interface}:{self.channel}"
        if self.host is not None:
            where += f"@{self.host}:{self.port}"
        return where

    def disconnect(self) -> None:
        """Stop the heartbeat first (the drive then falls safe by itself), then shut the bus down.
        Idempotent; always leaves the bus closed even if stopping the heartbeat fails."""
        with self._lock:
            network, self._network = self._network, None
            task, self._heartbeat_task = self._heartbeat_task, None
            self._watch = None
        if network is None:
            return
        try:
            if task is not None:
                task.stop()
        finally:
            for node_id in list(network.nodes):
                del network[node_id]
            network.disconnect()

    def __enter__(self) -> "CanBus":
        return self.connect()

    def __exit__(self, *exc_info) -> None:
        self.disconnect()

    # -- access -------------------------------------------------------------------------------------
    @property
    def connected(self) -> bool:
        return self._network is not None

    @property
    def network(self) -> canopen.Network:
        """The canopen.Network on this bus; raises NotConnectedError before connect()."""
        network = self._network
        if network is None:
            raise NotConnectedError(
                f"CAN bus {self.interface}:{self.channel} is not connected (call CanBus.connect() first)"
            )
        return network

    def heartbeat_producing(self) -> bool:
        """True while the service heartbeat task is running (its send thread alive, where the
        transport uses one): the drive falls to FAULT (EMCY 0x8130) 0.5 s after it stops."""
        task = self._heartbeat_task
        if task is None or self._network is None:
            return False
        inner = getattr(task, "_task", task)  # canopen wraps python-can's cyclic task
        thread = getattr(inner, "thread", None)
        if thread is not None and not thread.is_alive():
            return False
        return not getattr(inner, "stopped", False)

    @property
    def heartbeat_cob_id(self) -> int:
        return HEARTBEAT_COB_BASE + self.service_node_id

    def __repr__(self) -> str:
        return f"CanBus({self._where()}, service_node_id={self.service_node_id}, connected={self.connected})"
