"""The bench's links: CAN bus, drive and load masters, DC supply, DAQ reader.

Drivers are chosen by settings strings (CAN interface, pyserial URLs); nothing here knows whether
the bench is emulated. `open()` opens every link in order; a link that fails closes what was opened
and raises BenchUnreachable naming the device, its address and what to check, and the bench stays
`unreachable` (a run is then refused naming it, see `unreachable_trip`).
"""

from __future__ import annotations

import contextlib
import logging
import time
from datetime import datetime, timezone

from drivers.canopen_bus import CanBus
from drivers.daq_reader import DaqReader
from drivers.dc_supply import ScpiSupply
from drivers.drive import DriveClient
from drivers.errors import DaqPortBusy, ForeignMasterError
from drivers.load_machine import LoadClient
from service.bench.errors import BenchError, BenchUnreachable
from service.bench.interlocks import Trip
from service.settings import Settings

log = logging.getLogger(__name__)


class BenchLinks:
    """The links to the bench's devices (module doc); None until opened."""

    def __init__(self, settings: Settings):
        self.settings = settings
        self.bus: CanBus | None = None
        self.drive: DriveClient | None = None
        self.load: LoadClient | None = None
        self.daq: DaqReader | None = None
        self.supply: ScpiSupply | None = None
        self.unreachable: dict[str, str] | None = None  # {device, address, hint, error} when open() failed

    def open(self) -> None:
        """Open every link; a link that fails raises BenchUnreachable naming the device, its address and
        what to check (nothing half-open is left behind)."""
        s = self.settings
        if not s.daq.url or not s.supply.url:
            raise BenchError("bench settings name no DAQ port (daq.url) or supply port (supply.url)")
        can_at = f"{s.can.interface} {s.can.channel}" + (f" at {s.can.host}:{s.can.port}" if s.can.host else "")
        steps = [
            (
                "CAN bus",
                can_at,
                "the CAN adapter or socketcand server is up and can.interface/channel/host/port name it",
                self._connect_bus,
            ),
            (
                f"drive (node {s.can.drive_node})",
                can_at,
                "the drive is powered, on the bus, and can.drive_node is its node id",
                self._connect_drive,
            ),
            (
                f"load machine (node {s.can.load_node})",
                can_at,
                "the load machine is powered, on the bus, and can.load_node is its node id",
                self._connect_load,
            ),
            ("DC supply", s.supply.url, "the supply is on and supply.url names its port", self._connect_supply),
            ("DAQ", s.daq.url, "the DAQ is plugged in and daq.url names its port", self._connect_daq),
        ]
        for device, address, hint, step in steps:
            try:
                step()
            except Exception as exc:
                self.close()
                if isinstance(exc, (ForeignMasterError, DaqPortBusy)):
                    # reached, but held by another master: the hint is to stop that one, not to check cables
                    hint = (
                        "another service or tool is master of it (one service per bench): stop that one"
                        if isinstance(exc, ForeignMasterError)
                        else "no other process holds the DAQ port (one service per bench): stop the one that does"
                    )
                self.unreachable = {
                    "device": device,
                    "address": address,
                    "hint": f"check that {hint}",
                    "error": f"{type(exc).__name__}: {exc}",
                }
                raise BenchUnreachable(
                    f"bench unreachable: {device} at {address} ({type(exc).__name__}: {exc}); check that {hint}"
                ) from exc
        self.unreachable = None

    def _connect_bus(self) -> None:
        s = self.settings
        self.bus = CanBus(
            s.can.interface,
            s.can.channel,
            host=s.can.host,
            port=s.can.port,
            bitrate=s.can.bitrate,
            service_node_id=s.can.service_node_id,
            heartbeat_period_ms=s.can.heartbeat_period_ms,
            **s.can.options,
        )
        # python-can logs every failed attempt as a warning; connect() says it once, with what to check
        can_log = logging.getLogger("can")
        level = can_log.level
        can_log.setLevel(logging.ERROR)
        try:
            self.bus.connect()
        finally:
            can_log.setLevel(level)

    def _connect_drive(self) -> None:
        self.drive = DriveClient(self.bus, self.settings.can.drive_node, sdo_timeout_s=self.settings.can.sdo_timeout_s)
        self.drive.connect()

    def _connect_load(self) -> None:
        self.load = LoadClient(self.bus, self.settings.can.load_node, sdo_timeout_s=self.settings.can.sdo_timeout_s)
        self.load.connect()

    def _connect_supply(self) -> None:
        self.supply = ScpiSupply(self.settings.supply.url, timeout_s=self.settings.supply.timeout_s)

    def _connect_daq(self) -> None:
        self.daq = DaqReader(self.settings.daq.url, max_buffered_samples=4096)  # little stale data before each setpoint
        self.daq.start()

    def disarm_heartbeat_consumers(self) -> None:
        """Drive and load no longer watch the service's heartbeat (0x1016): they do not fault when it
        stops with an orderly close. open() arms the consumers again."""
        for device in (self.drive, self.load):
            try:
                device.disarm_heartbeat_consumer()
            except Exception as exc:  # noqa: BLE001 - the device may be gone; it then faults as it should
                log.warning(
                    "%s node %d: heartbeat consumer not disarmed (%s): it will fault when the "
                    "service's heartbeat stops",
                    device.device_kind,
                    device.node_id,
                    exc,
                )

    def close(self) -> None:
        """The links closed (the service heartbeat stops last, with the bus)."""
        for part in (self.daq, self.supply):
            with contextlib.suppress(Exception):
                if part is not None:
                    part.close()
        with contextlib.suppress(Exception):
            if self.bus is not None:
                self.bus.disconnect()

    # --- reachability ------------------------------------------------------------------------------
    def check_reachable(self) -> None:
        """Before a run is accepted: BenchUnreachable naming the device and what to check while the bench
        could not be reached at start (a run would only fail later)."""
        if self.unreachable is not None:
            raise BenchUnreachable(self.unreachable_trip().reason)

    def unreachable_trip(self) -> Trip:
        """The bench not reached at start as a trip that forbids runs (for refusals and the status)."""
        u = self.unreachable
        return Trip(
            "bench_unreachable",
            f"{u['device']} at {u['address']} unreachable at start ({u['error']}); "
            f"{u['hint']}, then restart the service",
            latched=False,
            at=datetime.now(timezone.utc).isoformat(timespec="seconds"),
            monotonic=time.monotonic(),
        )
