"""The emulator process: wires physics, firmware, CAN, DAQ pty and supply together and runs them.

Threads: the plant thread (pieces of physics + frame encoding in one numba call -> pty, setpoints
taken at piece starts), the DAQ writer (blocking in fast mode, continuous from the DAQ's FIFO in
paced mode: plant_emulator/daq_stream.py), the canopen notifier (SDO server, NMT, heartbeats of the
two LocalNodes), the socketcand server (accept/read + virtual-bus pump), the SCPI server, the fault
control socket, and a heartbeat watchdog. The main thread waits for SIGTERM/SIGINT and then closes
everything; the exit code is 0.

Plant time is the DAQ sample counter. The drive takes at most one setpoint event per piece start
(drive_firmware.py: each event is one toggle of the DAQ sync flag; two at one sample would cancel).

`speedup` 0 (fast): the plant runs as fast as the DAQ reader consumes (blocking pty writes). A
setpoint is applied at a chunk start (256 samples) and each one is its own chunk; while no setpoint
event waits, FRAME_BATCH_CHUNKS chunks run in one numba call and one write, which keeps the Python
work per simulated second small (an SDO write that arrives meanwhile is applied at the next block
start, still at a chunk start and still one toggle per write). A reader that keeps up loses nothing;
one that stops reading does not stop the bench for ever: once the pty has taken nothing for
FAST_STALL_S of wall time (the paced DAQ's FIFO depth), the plant runs in real time, a chunk at a time,
and drops its frames (a DAQ overflowing), so a drive and a load machine left alone (a service killed
mid-run: heartbeat lost, the load braking to standstill) go on in plant time as on a real bench. As
soon as the pty takes bytes again, it runs as fast as it is read; the reader sees what was queued
before the stall, then a sequence gap.

`speedup` X > 0 (paced, like a real drive and DAQ): the plant simulates the samples that are due by
the wall clock (X times real time), behind it as a real DAQ delivers a sample after it happened, in
pieces of about PACED_WAKE_S of wall time; the thread also wakes at once when a setpoint is written
(`DriveFirmware.setpoint_written`). The samples due by then are simulated with the setpoints before
the write, and the event applies from the next sample on, so a setpoint takes effect within about a
ms of its write at 1x and each sample leaves within a few ms of its time. With several events
pending, pieces of EVENT_PIECE_SAMPLES apply them one per piece start. The firmware's chunk-rate
task runs at each piece start (and every chunk within a piece); the 0x2010 mean, the published speed,
the fault tick and the scope take each piece's own length.
"""

from __future__ import annotations

import argparse
import collections
import json
import logging
import math
import os
import signal
import sys
import threading
import time
import uuid

import canopen
import numpy as np

from drivers import DRIVE_EDS, LOAD_EDS
from drivers.blas_threads import one_blas_thread
from drivers.daq_protocol import FRAME_DTYPE

from . import physics as ph
from . import scenario as scn
from .daq_stream import STALLED, STOPPED, DaqPty
from .drive_firmware import DriveFirmware
from .faults import ControlServer, FaultState
from .load_machine import LoadMachineFirmware
from .scope import Scope
from .scpi_supply import DcSupply, ScpiServer
from .slcan_server import SlcanServer
from .socketcand_server import SocketcandServer

log = logging.getLogger("plant_emulator")

DRIVE_NODE = 5
LOAD_NODE = 6
CHUNK_SAMPLES = 256  # physics chunk: setpoints are taken at chunk starts (16 ms at 16 kHz)
FRAME_BATCH_CHUNKS = 16  # chunks per numba call + write when running fast (256 ms plant time)
U_REF_MEAN_SAMPLES = 1024  # 0x2010: mean over the last 1024 periods
PACED_WAKE_S = 0.002  # paced: the plant thread simulates what is due this often (wall time)
EVENT_PIECE_SAMPLES = 16  # paced: piece length while setpoint events wait (one applies per piece start)
PACED_MAX_PIECE_SAMPLES = 4096  # paced: most samples per numba call when catching up
PACED_MAX_WAIT_S = 0.1  # paced: longest sleep (stop and very slow speedups)
PACED_BEHIND_RESET_S = 1.0  # paced: this far behind the wall clock (machine busy), do not catch up
DAQ_FIFO_S = 0.25  # paced: the DAQ's FIFO holds this much stream (wall time) before it overflows
DAQ_FIFO_MIN_BYTES = 1 << 16
FAST_STALL_S = DAQ_FIFO_S  # fast: the pty took nothing for this long (nobody reads): real time, frames dropped
WATCHDOG_PERIOD_S = 0.02
RAD_S_TO_RPM = 60.0 / (2.0 * math.pi)


class Emulator:
    def __init__(
        self,
        sc: scn.Scenario,
        speedup: float = 1.0,
        can_port: int = 0,
        supply_port: int = 0,
        chunk_samples: int = CHUNK_SAMPLES,
        control_port: int = 0,
    ):
        self.scenario = sc
        self.speedup = float(speedup)
        self.chunk = int(chunk_samples)
        self.params, self.tab = scn.build(sc)
        self.sample_rate_hz = sc.sample_rate_hz
        self.plant = ph.Plant(self.params, self.tab, noise_seed=sc.seed if sc.seed is not None else 0, chunk=self.chunk)
        self.sp = ph.new_setpoints(0.0)
        self.stop_event = threading.Event()
        self.samples = 0
        self.supply = DcSupply(sc.udc_v, seed=sc.seed)
        self.scpi = ScpiServer(self.supply, port=supply_port)
        self.bus_channel = f"ripplecal-emulator-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        self.can_server = SocketcandServer(self.bus_channel, port=can_port)
        # the same bus as an slcan adapter (python-can's slcan interface over socket://): a second transport
        self.slcan_server = SlcanServer(self.bus_channel)
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.1
        self.network.connect(interface="virtual", channel=self.bus_channel, receive_own_messages=False)
        fw = sc.section("firmware")
        self.drive = DriveFirmware(self.network, DRIVE_NODE, str(DRIVE_EDS), udc_min_v=float(fw.get("udc_min_v", 6.0)))
        self.load = LoadMachineFirmware(
            self.network,
            LOAD_NODE,
            str(LOAD_EDS),
            ramp_rpm_per_s=float(self.params[ph.P_LOAD_RAMP]) * 60.0 / (2.0 * math.pi),
        )
        # paced, the DAQ's FIFO is sized in wall time: what the reader may fall behind before frames drop
        fifo_bytes = int(DAQ_FIFO_S * self.sample_rate_hz * self.speedup) * ph.FRAME_BYTES
        self.daq = DaqPty(max_pending_bytes=max(DAQ_FIFO_MIN_BYTES, fifo_bytes))
        self.scope = Scope(self.sample_rate_hz)
        self.faults = FaultState(self, sc.section("faults"), seed=sc.seed)
        self.control = ControlServer(self.faults, port=control_port)
        self.can_server.delay_for = self.faults.sdo_delay_for
        self.slcan_server.delay_for = self.faults.sdo_delay_for
        self._threads: list[threading.Thread] = []
        self._closed = False

    # -- endpoints -----------------------------------------------------------------------------------
    def endpoints(self) -> dict:
        return {
            "can": {
                "interface": "socketcand",
                "host": self.can_server.host,
                "port": self.can_server.port,
                "channel": self.can_server.channel,
            },
            # the same bus for python-can's slcan interface: can.Bus(interface="slcan", channel=<this>)
            "slcan": {"interface": "slcan", "channel": self.slcan_server.url},
            "daq": self.daq.link,  # stable path (symlink) that survives reconnects
            "daq_device": self.daq.name,
            "supply": self.scpi.url,
            "control": self.control.url,
            "drive_node": DRIVE_NODE,
            "load_node": LOAD_NODE,
            "sample_rate_hz": int(round(self.sample_rate_hz)),
            "scenario": self.scenario.name,
            "seed": self.scenario.seed,
        }

    # -- lifecycle -----------------------------------------------------------------------------------
    def start(self) -> "Emulator":
        warm_up()
        self.can_server.start()
        self.slcan_server.start()
        self.scpi.start()
        self.control.start()
        self.drive.boot()
        self.load.boot()
        self._threads = [
            threading.Thread(target=self._plant_loop, name="plant", daemon=True),
            threading.Thread(target=self._watchdog, name="heartbeat-watchdog", daemon=True),
            threading.Thread(target=self.drive.actuals_loop, args=(self.stop_event,), name="drive-tpdo", daemon=True),
        ]
        for t in self._threads:
            t.start()
        return self

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.stop_event.set()
        for t in self._threads:
            t.join(timeout=3.0)
        for closer in (
            self.drive.shutdown,
            self.load.shutdown,
            self.network.disconnect,
            self.can_server.close,
            self.slcan_server.close,
            self.scpi.close,
            self.control.close,
            self.daq.close,
        ):
            try:
                closer()
            except Exception:
                log.exception("error while closing")

    # -- threads -------------------------------------------------------------------------------------
    def _watchdog(self) -> None:
        woke = time.monotonic()
        while not self.stop_event.wait(WATCHDOG_PERIOD_S):
            now = time.monotonic()
            stalled_s, woke = max(0.0, now - woke - WATCHDOG_PERIOD_S), now  # our own lateness
            try:
                self.drive.check_heartbeat(now, stalled_s)
                self.load.check_heartbeat(now, stalled_s)
            except Exception:
                log.exception("heartbeat watchdog")

    def _plant_loop(self) -> None:
        try:
            self._run_plant()
        except Exception:
            log.exception("plant thread died")
            self.stop_event.set()

    def _run_plant(self) -> None:
        if self.speedup > 0.0:
            self._run_paced()
        else:
            self._run_fast()

    # -- one piece of plant: setpoints at its start, physics + frames, published measurements --------
    def _alloc_pieces(self, max_samples: int) -> None:
        n = self.chunk
        self._frames = np.empty(max_samples * ph.FRAME_BYTES, dtype=np.uint8)
        self._summary = np.zeros((-(-max_samples // n), ph.N_SUMMARY))
        self._no_trace = np.zeros((0, ph.N_TRACE))
        self._zeros = np.zeros(max_samples)
        self._noise_on = self.params[ph.P_NOISE] > 0.0
        # 0x2010: (u_d sum, u_q sum, samples) per summary row, the newest covering U_REF_MEAN_SAMPLES
        self._uref_rows: collections.deque[tuple[float, float, int]] = collections.deque()
        self._uref_samples = 0

    def _piece_start(self) -> float:
        """Supply voltage and the scenario's timed faults at the start of a piece; returns U_dc."""
        udc = self.supply.actual_v()
        self.faults.tick(self.samples / self.sample_rate_hz)
        return udc

    def _take_setpoints(self, udc: float, take_event: bool = True) -> bool:
        """The drive's and the load's setpoints for the next piece (at most one event: True if one)."""
        applied = self.drive.chunk_setpoints(self.sp, udc, take_event=take_event)
        self.load.chunk_setpoints(self.sp)
        return applied

    def _advance(self, k: int, udc: float) -> bytes:
        """Simulate k samples with the setpoints taken, publish the firmware's measurements, and return
        the DAQ bytes as the wire delivers them."""
        n = self.chunk
        noise = self.plant.rng.standard_normal(k) if self._noise_on else self._zeros[:k]
        scoping = self.scope.recording  # the oscilloscope wants this piece's samples
        trace = np.zeros((k, ph.N_TRACE)) if scoping else self._no_trace
        rows = -(-k // n)
        frames, summary = self._frames[: k * ph.FRAME_BYTES], self._summary[:rows]
        ph.simulate(
            self.plant.x,
            self.params,
            self.tab,
            self.sp,
            self.drive.theta_schedule(),
            noise,
            n,
            self.samples,
            frames,
            summary,
            trace,
        )
        if scoping:
            self.scope.feed(trace)
        self.samples += k
        # publish the firmware's measurements (read by SDO); rows hold n samples, the last one the rest
        uref = self._uref_rows
        for row in range(rows):
            count = min(n, k - row * n)
            uref.append((float(summary[row, ph.Y_UD_SUM]), float(summary[row, ph.Y_UQ_SUM]), count))
            self._uref_samples += count
            while self._uref_samples - uref[0][2] >= U_REF_MEAN_SAMPLES:
                self._uref_samples -= uref.popleft()[2]
        filled = self._uref_samples
        last, last_count = summary[rows - 1], k - (rows - 1) * n
        speed_rpm = float(last[ph.Y_OMEGA_SUM]) / last_count * RAD_S_TO_RPM
        self.drive.publish(
            speed_rpm,
            float(last[ph.Y_TORQUE_EST_SUM]) / last_count,
            udc,
            sum(r[0] for r in uref) / filled,
            sum(r[1] for r in uref) / filled,
            math.hypot(float(self.plant.x[ph.X_ID]), float(self.plant.x[ph.X_IQ])),  # |i_dq| at the piece's end
        )
        self.load.publish(speed_rpm, float(last[ph.Y_LOAD_TORQUE_SUM]) / last_count)
        self.faults.miswire(frames.view(FRAME_DTYPE))  # in place: a view of the bytes as frames
        return self.faults.apply_daq(frames.tobytes())

    # -- the two disciplines -------------------------------------------------------------------------
    def _run_fast(self) -> None:
        """--speedup 0: blocks of chunks as fast as the DAQ reader consumes (blocking writes). While
        nobody reads (the pty has taken nothing for FAST_STALL_S), the plant runs in real time, chunk
        by chunk, and its frames are dropped, until the reader reads again."""
        n, batch = self.chunk, FRAME_BATCH_CHUNKS
        self._alloc_pieces(n * batch)
        out = bytearray()
        out_limit = n * batch * ph.FRAME_BYTES
        self.daq.start_writer(self.stop_event)
        stalled_at: float | None = None  # wall time the DAQ stalled (nobody reads); None: it is read
        pace = (0.0, 0)  # while stalled: (wall time, plant sample) the 1x clock started at
        while not self.stop_event.is_set():
            udc = self._piece_start()
            # one chunk while a setpoint event waits (it is applied at this chunk's start, the next one
            # at the next chunk's start) or while running in real time; a whole block otherwise
            m = 1 if self.drive.has_pending() or stalled_at is not None else batch
            self._take_setpoints(udc)
            out += self._advance(m * n, udc)
            if len(out) < out_limit and self.drive.has_pending() and stalled_at is None:
                continue  # keep single event chunks together in one write
            data = bytes(out)
            out.clear()
            if self.faults.daq_disconnected:
                # nobody can read: no backpressure, so run in real time (frames are lost anyway)
                self.stop_event.wait(len(data) / ph.FRAME_BYTES / self.sample_rate_hz)
                continue
            if stalled_at is not None:
                if self.daq.write_progress_at <= stalled_at:
                    # still nobody reads: the plant keeps real time (a drive does not wait for its DAQ's
                    # reader: a load machine braking after a lost heartbeat must come to its standstill)
                    self.daq.drop(data)
                    pace = self._keep_real_time(*pace)
                    continue
                log.info(
                    "DAQ read again: running as fast as it is read (%d frames dropped so far)", self.daq.frames_dropped
                )
                stalled_at = None  # this batch is the first after the gap
            result = self.daq.offer(data, stall_s=FAST_STALL_S)
            if result == STOPPED:
                break
            if result == STALLED:
                stalled_at = time.monotonic()
                pace = (stalled_at, self.samples)
                self.daq.drop(data)
                log.info("DAQ not read for %.2f s: the plant runs in real time, its frames are dropped", FAST_STALL_S)

    def _keep_real_time(self, t0: float, plant_t0: int) -> tuple[float, int]:
        """Sleep until the wall clock has caught up with the plant (1x since (t0, plant_t0)); returns the
        clock's origin, moved to now when the machine was too busy to keep up (no catching up)."""
        now = time.monotonic()
        ahead_s = t0 + (self.samples - plant_t0) / self.sample_rate_hz - now
        if ahead_s < -PACED_BEHIND_RESET_S:
            return now, self.samples
        if ahead_s > 0.0:
            self.stop_event.wait(ahead_s)
        return t0, plant_t0

    def _run_paced(self) -> None:
        """--speedup X > 0: the samples due by the wall clock, in pieces of ~PACED_WAKE_S, cut where a
        setpoint is written; written to the DAQ's FIFO at once."""
        rate = self.sample_rate_hz * self.speedup  # samples per wall second
        wake_samples = max(1, int(round(PACED_WAKE_S * rate)))
        self._alloc_pieces(PACED_MAX_PIECE_SAMPLES)
        written = self.drive.setpoint_written
        t0, plant_t0 = time.monotonic(), self.samples
        event_from = None  # first sample the pending setpoint events may apply at (due when first seen)
        while not self.stop_event.is_set():
            written.clear()  # before looking: a write from now on wakes the wait below
            now = time.monotonic()
            due = plant_t0 + int((now - t0) * rate)
            if due - self.samples > rate * PACED_BEHIND_RESET_S:
                # fell behind (machine busy): do not catch up; pending setpoints apply from here on
                t0, plant_t0, event_from = now, self.samples, None
                continue
            pending = self.drive.has_pending()
            if not pending:
                event_from = None
            elif event_from is None:
                event_from = max(due, self.samples)  # written by now: effective from the next sample
            take = pending and self.samples >= event_from
            if pending and not take:
                end = event_from  # the samples before the write, with the setpoints before it
            else:
                want = EVENT_PIECE_SAMPLES if take else wake_samples
                if due - self.samples < want:
                    # not due yet: sleep until it is, or until a setpoint is written
                    wait_s = t0 + (self.samples + want - plant_t0) / rate - now
                    written.wait(min(max(wait_s, 0.0), PACED_MAX_WAIT_S))
                    continue
                end = due
            k = min(end - self.samples, PACED_MAX_PIECE_SAMPLES)
            udc = self._piece_start()
            if self._take_setpoints(udc, take_event=take) and self.drive.has_pending():
                k = min(k, EVENT_PIECE_SAMPLES)  # the next event at the next piece start, soon
            self.daq.write_paced(self._advance(k, udc))


def warm_up() -> None:
    """Compile (or load from numba's cache) the chunk function before the endpoints are announced."""
    sc = scn.load(scn.DEFAULT_SCENARIO)
    p, tab = scn.build(sc)
    plant = ph.Plant(p, tab)
    plant.run(ph.new_setpoints(12.0), 4)


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(
        prog="python -m plant_emulator",
        description="Emulated PMSM test bench: socketcand CANopen, DAQ pty, SCPI supply.",
    )
    ap.add_argument("--scenario", default=scn.DEFAULT_SCENARIO, help="scenario name or TOML path (default paper-bench)")
    ap.add_argument("--seed", type=int, default=None, help="perturb the truth within the scenario's [seed] ranges")
    ap.add_argument(
        "--speedup",
        type=float,
        default=1.0,
        help="X times real time, paced like a real drive and DAQ: setpoints take effect at the next "
        "control period after their write, and what the reader leaves unread for more than "
        "0.25 s (the DAQ's FIFO) is dropped in whole frames. Measured on 2 cores with a DaqReader "
        "consuming as fast as it can: no frame lost at 1x, 5x, 10x or 20x (beyond about 170x the "
        "emulator itself falls behind); 0 = as fast as the DAQ reader consumes, the way to run "
        "faster than real time (while nobody reads for 0.25 s: real time, frames dropped) "
        "(default 1)",
    )
    ap.add_argument("--can-port", type=int, default=0, help="socketcand TCP port on 127.0.0.1 (0: free port)")
    ap.add_argument("--supply-port", type=int, default=0, help="SCPI TCP port on 127.0.0.1 (0: free port)")
    ap.add_argument(
        "--control-port", type=int, default=0, help="fault control socket (JSON lines) on 127.0.0.1 (0: free port)"
    )
    ap.add_argument("--log-level", default="WARNING", help="logging level on stderr (default WARNING)")
    ap.add_argument(
        "--exit-on-stdin-eof",
        action="store_true",
        help="stop when stdin reaches EOF: a parent holding the pipe's other end takes the emulator "
        "with it when it dies, also by kill -9 (the kernel closes the pipe)",
    )
    args = ap.parse_args(argv)
    if args.speedup < 0:
        ap.error("--speedup must be >= 0")
    return args


STOP_LINE = b"stop\n"  # what a parent writes before it closes the pipe in an orderly stop


def _watch_parent_pipe(stop: threading.Event) -> None:
    """Block on stdin; EOF (or an error) means the parent is gone: stop like on SIGTERM. An orderly parent says
    STOP_LINE first (an info line); EOF without it is a parent that died (a warning: kill -9, a crash)."""
    asked = False
    try:
        while chunk := sys.stdin.buffer.read1(4096):
            asked = asked or STOP_LINE.strip() in chunk
    except (OSError, ValueError):
        pass
    if asked:
        log.info("the parent asked it to stop; stopping")
    else:
        log.warning("stdin closed without a stop: the parent is gone; stopping")
    stop.set()


def main(argv=None) -> int:
    args = parse_args(argv)
    one_blas_thread()
    logging.basicConfig(
        level=getattr(logging, str(args.log_level).upper(), logging.WARNING),
        stream=sys.stderr,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
    )
    stop = threading.Event()

    def on_signal(signum, frame):
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    if args.exit_on_stdin_eof:
        threading.Thread(target=_watch_parent_pipe, args=(stop,), name="parent-pipe", daemon=True).start()
    sc = scn.load(args.scenario, seed=args.seed)
    emu = Emulator(
        sc, speedup=args.speedup, can_port=args.can_port, supply_port=args.supply_port, control_port=args.control_port
    )
    try:
        emu.start()
        sys.stdout.write(json.dumps(emu.endpoints()) + "\n")
        sys.stdout.flush()
        while not stop.is_set() and not emu.stop_event.is_set():
            stop.wait(0.2)
    finally:
        emu.close()
    return 0 if not emu.stop_event.is_set() or stop.is_set() else 1
