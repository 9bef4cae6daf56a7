"""The bench's links: CAN bus, drive and load masters, DC supply, DAQ reader.

Drivers are chosen by settings strings (CAN interface, pyserial URLs); nothing here knows whether
the bench is emulated but the DAQ's frame-rate check (skipped for the service's own emulator, whose
rate the settings take from it). `open()` opens every link in order; a link that fails closes what
was opened and raises BenchUnreachable naming the device, its address, what to check and how the
devices were left, and the bench stays `unreachable` (a run is then refused naming it, see
`unreachable_trip`).

The devices are left as found until the bench is whole: the drive and the load consume the service's
heartbeat (0x1016) and fault when it stops, and one that consumes it from power-up starts watching at
the first heartbeat it hears. So the service's heartbeat is not produced, and no consumer armed,
until every link is open and checked (both nodes with the identity of their EDS, the supply
answering, the DAQ streaming at its configured rate); a failure before then lets go of the bus
without a heartbeat ever sent, and one while arming disarms what was armed. Every orderly close
disarms the consumers again (DESIGN section 6), but not on a device still enabled: its consumer is
then what stops it when the heartbeat does.
"""

from __future__ import annotations

import contextlib
import logging
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Callable

from drivers.canopen_bus import CanBus
from drivers.cia402 import State402
from drivers.cia402_master import Cia402Master
from drivers.daq_reader import DaqReader, rate_text
from drivers.dc_supply import ScpiSupply
from drivers.drive import DriveClient
from drivers.errors import (
    DaqNotSerialPort,
    DaqNotStreaming,
    DaqPortBusy,
    DaqRateMismatch,
    ForeignMasterError,
    SdoAbortError,
    WrongDeviceError,
)
from drivers.load_machine import LoadClient
from service.bench.errors import BenchError, BenchUnreachable
from service.bench.trips import Trip
from service.settings import Settings

log = logging.getLogger(__name__)

LEFT_AS_FOUND = "drive and load left as found: heartbeat consumers not armed"

# states with the power stage off: a consumer disarmed there cannot leave a powered device unwatched
POWER_OFF_STATES = frozenset(
    {
        State402.NOT_READY_TO_SWITCH_ON,
        State402.SWITCH_ON_DISABLED,
        State402.READY_TO_SWITCH_ON,
        State402.FAULT,
    }
)


@dataclass(frozen=True)
class OpenLinks:
    """The links of a bench that open() reached whole (BenchLinks.opened): none of them missing."""

    bus: CanBus
    drive: DriveClient
    load: LoadClient
    daq: DaqReader
    supply: ScpiSupply


class BenchLinks:
    """The links to the bench's devices (module doc); None until opened (`opened()`: all of them)."""

    def __init__(self, settings: Settings, on_answer: Callable[[], None] | None = None):
        self.settings = settings
        # given to drive and load: called after every SDO transfer they answered (the bench watchdog's
        # sign that a run's loop is at work on a slow bus)
        self.on_answer = on_answer
        self.bus: CanBus | None = None
        self.drive: DriveClient | None = None
        self.load: LoadClient | None = None
        self.daq: DaqReader | None = None
        self.supply: ScpiSupply | None = None
        # {device, address, hint, error, left (how the devices were left)} when open() failed
        self.unreachable: dict[str, str] | None = None
        self._armed: dict[Cia402Master, int] = {}  # devices whose heartbeat consumer we armed: 0x1016:1 as found
        self._verdict = "unreachable"  # or "not as the bench file says", when open() failed
        self._disarm_tried = False  # disarm_heartbeat_consumers ran since the consumers were armed

    def open(self) -> None:
        """Open every link, then arm the heartbeat consumers (module doc); a link that fails raises
        BenchUnreachable naming the device, its address, what to check and how the devices were left
        (nothing half-open is left behind)."""
        s = self.settings
        daq_url, supply_url = s.daq.url, s.supply.url
        if not daq_url or not supply_url:
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
            (
                "DC supply",
                supply_url,
                "the supply is on and supply.url names its port",
                lambda: self._connect_supply(supply_url),
            ),
            ("DAQ", daq_url, "the DAQ is plugged in and daq.url names its port", lambda: self._connect_daq(daq_url)),
            (
                "drive and load heartbeat consumers",
                can_at,
                "drive and load are on the bus and accept 0x1016 writes",
                self._arm_heartbeat_consumers,
            ),
        ]
        for device, address, hint, step in steps:
            try:
                step()
            except Exception as exc:
                left = self._leave_as_found()
                what, hint = self._describe_failure(exc, device, hint)
                self.unreachable = {
                    "device": device,
                    "address": address,
                    "hint": f"check that {hint}",
                    "error": what,
                    "left": left,
                }
                # reached, but not the bench the file describes: "unreachable" would send people to the cables
                self._verdict = (
                    "not as the bench file says"
                    if isinstance(exc, (WrongDeviceError, DaqRateMismatch))
                    else "unreachable"
                )
                raise BenchUnreachable(
                    f"bench {self._verdict}: {device} at {address} ({what}); check that {hint}; {left}"
                ) from exc
        self.unreachable = None

    def _describe_failure(self, exc: Exception, device: str, hint: str) -> tuple[str, str]:
        """(what went wrong, what to check) for the one line: the driver's error, with the fix where the
        kind of error says more than the step's default hint."""
        s = self.settings
        what = f"{type(exc).__name__}: {exc}"
        if isinstance(exc, ForeignMasterError):
            # reached, but held by another master: the hint is to stop that one, not to check cables
            hint = "another service or tool is master of it (one service per bench): stop that one"
        elif isinstance(exc, DaqPortBusy):
            hint = "no other process holds the DAQ port (one service per bench): stop the one that does"
        elif isinstance(exc, WrongDeviceError):
            key, kind = ("drive_node", "drive") if device.startswith("drive") else ("load_node", "load machine")
            hint = f"can.{key} is the {kind}'s node id (are can.drive_node and can.load_node swapped?)"
        elif isinstance(exc, DaqNotSerialPort):
            hint = "daq.url names the DAQ's serial port (e.g. /dev/ttyACM0 or a /dev/serial/by-id/ path)"
        elif isinstance(exc, DaqNotStreaming):
            hint = "daq.url names the DAQ's port (not another device's) and the DAQ is powered and streaming"
        elif isinstance(exc, DaqRateMismatch):
            what = (
                f"the DAQ streams {rate_text(exc.measured_hz)} frames/s, the bench file says "
                f"{rate_text(s.daq.sample_rate_hz)} (daq.sample_rate_hz)"
            )
            hint = (
                f"daq.sample_rate_hz is the rate the DAQ is set to (it streams {rate_text(exc.measured_hz)} "
                f"frames/s), or set the DAQ to {rate_text(s.daq.sample_rate_hz)} frames/s"
            )
        return what, hint

    def _leave_as_found(self) -> str:
        """After a failed open: 0x1016 written back as found where it was armed (no heartbeat was sent
        yet: the service's starts after the last consumer is armed, so nothing is watching it), the
        links closed; how the devices were left, for the error."""
        stuck = self._disarm(restore=True)
        self._armed = {}  # what could not be written back is said; close() tries no second time
        self.close()
        return "; ".join(stuck) if stuck else LEFT_AS_FOUND

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
            # no heartbeat yet: a device that consumes it from power-up would fault if we let go now
            self.bus.connect(heartbeat=False)
        finally:
            can_log.setLevel(level)

    def _opened_bus(self) -> CanBus:
        """The bus, for the steps of open() after its first (which opened it)."""
        if self.bus is None:
            raise BenchError("the CAN bus is not open")
        return self.bus

    def _connect_drive(self) -> None:
        self.drive = DriveClient(
            self._opened_bus(), self.settings.can.drive_node, sdo_timeout_s=self.settings.can.sdo_timeout_s
        )
        self.drive.on_answer = self.on_answer
        self.drive.connect(arm_consumer=False)

    def _connect_load(self) -> None:
        self.load = LoadClient(
            self._opened_bus(), self.settings.can.load_node, sdo_timeout_s=self.settings.can.sdo_timeout_s
        )
        self.load.on_answer = self.on_answer
        self.load.connect(arm_consumer=False)

    def _connect_supply(self, url: str) -> None:
        self.supply = ScpiSupply(url, timeout_s=self.settings.supply.timeout_s)
        self.supply.identify()  # answering, not just a port that opens

    def _connect_daq(self, url: str) -> None:
        daq = self.settings.daq
        self.daq = DaqReader(url, max_buffered_samples=4096)  # little stale data before each setpoint
        self.daq.start()
        if self.settings.bench_mode == "emulate":
            # our own emulator, whose rate the settings took from it; paced or not, as --speedup says
            self.daq.wait_first_frame(daq.read_timeout_s)
            return
        check = self.daq.check_frame_rate(daq.sample_rate_hz, daq.read_timeout_s)
        if not check.judged:
            log.info(
                "DAQ frame rate not judged: it streams %s frames/s, far above the %s of daq.sample_rate_hz: a "
                "stream as fast as it is read (an emulator at --speedup 0), whose sample clock the wall clock "
                "cannot judge",
                rate_text(check.measured_hz),
                rate_text(check.expected_hz),
            )

    def _arm_heartbeat_consumers(self) -> None:
        """The bench is whole: drive and load consume the service's heartbeat, which starts now."""
        links = self.opened()
        for device in (links.drive, links.load):
            found = device.heartbeat_consumer()
            self._armed[device] = found  # before the write: a write whose answer was lost may have armed it
            try:
                device.arm_heartbeat_consumer()
            except SdoAbortError:
                del self._armed[device]  # refused: nothing was written
                raise
        self._disarm_tried = False
        links.bus.start_heartbeat()  # last: nothing watches it before the bench is whole

    def disarm_heartbeat_consumers(self) -> None:
        """Drive and load no longer watch the service's heartbeat (0x1016): they do not fault when it
        stops with an orderly close. A device still enabled keeps its consumer (module doc). open()
        arms the consumers again."""
        self._disarm_tried = True
        for failure in self._disarm():
            log.warning("%s", failure)

    def _disarm(self, restore: bool = False) -> list[str]:
        """Disarm every consumer we armed that can be (the power stage off): 0x1016:1 = 0, or as found
        (restore, only while the service's heartbeat has never been sent); what could not be, said."""
        failures: list[str] = []
        for device, found in list(self._armed.items()):
            where = f"{device.device_kind} node {device.node_id}"
            try:
                state = device.state()
                if state not in POWER_OFF_STATES:
                    failures.append(
                        f"{where} still {state.name}: its heartbeat consumer left armed, so it falls safe "
                        "(FAULT) when the service's heartbeat stops"
                    )
                    continue
                if restore:
                    device.set_heartbeat_consumer(found)
                else:
                    device.disarm_heartbeat_consumer()
            except Exception as exc:  # noqa: BLE001 - the device may be gone; it then faults as it should
                failures.append(
                    f"{where}: heartbeat consumer not written back as found ({exc}); it never heard the "
                    "service's heartbeat, so it has nothing to fault on"
                    if restore
                    else f"{where}: heartbeat consumer not disarmed ({exc}): it will fault when the service's "
                    "heartbeat stops (a fault reset is then needed)"
                )
                continue
            del self._armed[device]
        return failures

    def close(self) -> None:
        """The links closed (the service heartbeat stops last, with the bus); consumers still armed
        are disarmed first where they can be (every orderly exit, whoever calls it)."""
        if self._armed and not self._disarm_tried:  # the bench's orderly close has tried (and said) it
            self.disarm_heartbeat_consumers()
        self._armed = {}
        for part in (self.daq, self.supply):
            with contextlib.suppress(Exception):
                if part is not None:
                    part.close()
        with contextlib.suppress(Exception):
            if self.bus is not None:
                self.bus.disconnect()

    def opened(self) -> OpenLinks:
        """Every link, for what needs the bench connected (its interlocks, a run, the status); BenchError
        naming what is missing while open() has not reached the bench whole."""
        bus, drive, load, daq, supply = self.bus, self.drive, self.load, self.daq, self.supply
        if bus is None or drive is None or load is None or daq is None or supply is None:
            links = (("CAN bus", bus), ("drive", drive), ("load machine", load), ("DAQ", daq), ("DC supply", supply))
            missing = ", ".join(name for name, link in links if link is None)
            raise BenchError(f"the bench is not connected: {missing} not open")
        return OpenLinks(bus, drive, load, daq, supply)

    # --- reachability ------------------------------------------------------------------------------
    def check_reachable(self) -> None:
        """Before a run is accepted: BenchUnreachable naming the device and what to check while the bench
        could not be reached at start (a run would only fail later)."""
        if self.unreachable is not None:
            raise BenchUnreachable(self.unreachable_trip().reason)

    def unreachable_trip(self) -> Trip:
        """The bench not reached at start as a trip that forbids runs (for refusals and the status); a
        bench never opened (no connect() yet) says so."""
        u = self.unreachable
        reason = (
            "the bench is not connected: its links were never opened"
            if u is None
            else f"{u['device']} at {u['address']} {self._verdict} at start ({u['error']}); "
            f"{u['hint']}, then restart the service; {u['left']}"
        )
        return Trip(
            "bench_unreachable",
            reason,
            latched=False,
            at=datetime.now(timezone.utc).isoformat(timespec="seconds"),
            monotonic=time.monotonic(),
        )
