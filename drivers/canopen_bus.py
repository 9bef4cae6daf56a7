"""One CAN bus with a canopen Network on it, and the service's own NMT heartbeat.

The transport is chosen by the python-can interface string alone (socketcand, socketcan, pcan, kvaser,
virtual, ...): the same code talks to the emulator and to a real bench. The heartbeat matters for
safety: the drive consumes it (0x1016) and drops to torque 0 when the service goes silent, so it is
produced for exactly as long as the bus is connected and stops when the service lets go of the bus.
"""
from __future__ import annotations

import threading
from typing import Any

import can
import canopen
from threadpoolctl import threadpool_limits

from drivers.errors import NotConnectedError

NMT_STATE_OPERATIONAL = 0x05
HEARTBEAT_COB_BASE = 0x700

NOTIFIER_CYCLE_S = 0.1
"""Receive-thread wake-up period: disconnect() waits for it, and the safety path must not hang ~1 s
(canopen's default) before the bus is really released."""


def one_blas_thread() -> None:
    """Run BLAS on one thread in this process, for good (call once at process start; both the
    service and the emulated devices do). OpenBLAS workers spin while they wait for work: on a
    loaded 2-core PC they kept the heartbeat thread off the CPU for over a second and the drive fell
    safe (EMCY 0x8130). Our least-squares problems have tens of columns: one thread is as fast."""
    threadpool_limits(limits=1)


# python-can keyword arguments that suit a transport unless the settings say otherwise (can.options):
# socketcand carries every frame as text over TCP; without tcp_tune (TCP_NODELAY and TCP_QUICKACK)
# Nagle's algorithm and delayed ACKs hold an SDO answer back by ~40 ms now and then
INTERFACE_DEFAULTS: dict[str, dict[str, Any]] = {"socketcand": {"tcp_tune": True}}


class CanBus:
    """A python-can bus, a canopen.Network on it, and the periodic service heartbeat.

    interface, channel, host, port, bitrate: passed to `can.Bus` (only those that are set), so every
    python-can transport works unchanged. service_node_id: our node id on the bus; the heartbeat goes
    out on COB-ID 0x700 + service_node_id with one byte 0x05 (operational) every heartbeat_period_ms.
    """

    def __init__(self, interface: str, channel: str | int, host: str | None = None, port: int | None = None,
                 bitrate: int | None = None, service_node_id: int = 1, heartbeat_period_ms: int = 100,
                 **bus_kwargs: Any):
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
        self._lock = threading.Lock()

    # -- lifecycle ----------------------------------------------------------------------------------
    def bus_kwargs(self) -> dict[str, Any]:
        """Arguments for can.Bus: the interface string decides the transport; unset options are left out
        so that each interface applies its own defaults (virtual has no host, socketcan no bitrate)."""
        kwargs: dict[str, Any] = {"interface": self.interface, "channel": self.channel,
                                  **INTERFACE_DEFAULTS.get(self.interface, {})}
        for key in ("host", "port", "bitrate"):
            value = getattr(self, key)
            if value is not None:
                kwargs[key] = value
        kwargs.update(self._extra_bus_kwargs)
        return kwargs

    def connect(self) -> "CanBus":
        """Open the bus, start the canopen notifier and the service heartbeat. Idempotent."""
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
            try:
                network.connect()
                self._heartbeat_task = network.send_periodic(
                    HEARTBEAT_COB_BASE + self.service_node_id, bytes([NMT_STATE_OPERATIONAL]),
                    self.heartbeat_period_ms / 1000.0)
            except BaseException:
                network.disconnect()
                raise
            self._network = network
            return self

    def disconnect(self) -> None:
        """Stop the heartbeat first (the drive then falls safe by itself), then shut the bus down.
        Idempotent; always leaves the bus closed even if stopping the heartbeat fails."""
        with self._lock:
            network, self._network = self._network, None
            task, self._heartbeat_task = self._heartbeat_task, None
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
                f"CAN bus {self.interface}:{self.channel} is not connected (call CanBus.connect() first)")
        return network

    def heartbeat_producing(self) -> bool:
        """True while the service heartbeat task is running (its send thread alive, where the
        transport uses one): the drive falls to FAULT (EMCY 0x8130) 0.5 s after it stops."""
        task = self._heartbeat_task
        if task is None or self._network is None:
            return False
        inner = getattr(task, "_task", task)          # canopen wraps python-can's cyclic task
        thread = getattr(inner, "thread", None)
        if thread is not None and not thread.is_alive():
            return False
        return not getattr(inner, "stopped", False)

    @property
    def heartbeat_cob_id(self) -> int:
        return HEARTBEAT_COB_BASE + self.service_node_id

    def __repr__(self) -> str:
        where = f"{self.interface}:{self.channel}"
        if self.host is not None:
            where += f"@{self.host}:{self.port}"
        return f"CanBus({where}, service_node_id={self.service_node_id}, connected={self.connected})"
