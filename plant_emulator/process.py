"""The emulator process: wires physics, firmware, CAN, DAQ pty and supply together and runs them.

Threads: the plant thread (blocks of physics + frame encoding in one numba call -> pty, setpoints
taken at block starts), the DAQ writer (fast mode), the canopen notifier (SDO server, NMT, heartbeats
of the two LocalNodes), the socketcand server (accept/read + virtual-bus pump), the SCPI server, the
fault control socket, and a heartbeat watchdog. The main thread waits for SIGTERM/SIGINT and then
closes everything; the exit code is 0.

Plant time is the DAQ sample counter. `speedup` 0: the plant runs as fast as the DAQ reader
consumes (blocking pty writes); X > 0: paced to X times real time on the wall clock.

Blocks: a setpoint is applied at a chunk start (256 samples) and each one is its own chunk. While no
setpoint event waits (and when not paced slowly), up to BLOCK_CHUNKS chunks run in one numba call;
an SDO write that arrives meanwhile is applied at the next block start, i.e. still at a chunk start
and still one toggle per write. This keeps the Python work per simulated second small.
"""
from __future__ import annotations

import argparse
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
from drivers.canopen_bus import one_blas_thread

from . import physics as ph
from . import scenario as scn
from .daq_stream import DaqPty
from .drive_firmware import DriveFirmware
from .faults import ControlServer, FaultState
from .load_machine import LoadMachineFirmware
from .scope import Scope
from .scpi_supply import DcSupply, ScpiServer
from .socketcand_server import SocketcandServer

log = logging.getLogger("plant_emulator")

DRIVE_NODE = 5
LOAD_NODE = 6
CHUNK_SAMPLES = 256           # physics chunk: setpoints are taken at chunk starts (16 ms at 16 kHz)
FRAME_BATCH_CHUNKS = 16       # chunks per numba call + write when running fast (256 ms plant time)
FAST_SPEEDUP = 8.0            # below this (paced, > 0) every chunk is written at once
U_REF_MEAN_SAMPLES = 1024     # 0x2010: mean over the last 1024 periods
WATCHDOG_PERIOD_S = 0.02
RAD_S_TO_RPM = 60.0 / (2.0 * math.pi)


class Emulator:
    def __init__(self, sc: scn.Scenario, speedup: float = 1.0, can_port: int = 0, supply_port: int = 0,
                 chunk_samples: int = CHUNK_SAMPLES, control_port: int = 0):
        self.scenario = sc
        self.speedup = float(speedup)
        self.chunk = int(chunk_samples)
        self.params, self.tab = scn.build(sc)
        self.sample_rate_hz = sc.sample_rate_hz
        self.plant = ph.Plant(self.params, self.tab, noise_seed=sc.seed if sc.seed is not None else 0,
                              chunk=self.chunk)
        self.sp = ph.new_setpoints(0.0)
        self.stop_event = threading.Event()
        self.samples = 0
        self.supply = DcSupply(sc.udc_v, seed=sc.seed)
        self.scpi = ScpiServer(self.supply, port=supply_port)
        self.bus_channel = f"ripplecal-emulator-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        self.can_server = SocketcandServer(self.bus_channel, port=can_port)
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.1
        self.network.connect(interface="virtual", channel=self.bus_channel, receive_own_messages=False)
        fw = sc.section("firmware")
        self.drive = DriveFirmware(self.network, DRIVE_NODE, str(DRIVE_EDS), udc_min_v=float(fw.get("udc_min_v", 6.0)))
        self.load = LoadMachineFirmware(self.network, LOAD_NODE, str(LOAD_EDS),
                                        ramp_rpm_per_s=float(self.params[ph.P_LOAD_RAMP]) * 60.0 / (2.0 * math.pi))
        self.daq = DaqPty()
        self.scope = Scope(self.sample_rate_hz)
        self.faults = FaultState(self, sc.section("faults"), seed=sc.seed)
        self.control = ControlServer(self.faults, port=control_port)
        self.can_server.delay_for = self.faults.sdo_delay_for
        self._threads: list[threading.Thread] = []
        self._closed = False

    # -- endpoints -----------------------------------------------------------------------------------
    def endpoints(self) -> dict:
        return {
            "can": {"interface": "socketcand", "host": self.can_server.host, "port": self.can_server.port,
                    "channel": self.can_server.channel},
            "daq": self.daq.link,            # stable path (symlink) that survives reconnects
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
        self.scpi.start()
        self.control.start()
        self.drive.boot()
        self.load.boot()
        self._threads = [threading.Thread(target=self._plant_loop, name="plant", daemon=True),
                         threading.Thread(target=self._watchdog, name="heartbeat-watchdog", daemon=True)]
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
        for closer in (self.drive.shutdown, self.load.shutdown, self.network.disconnect, self.can_server.close,
                       self.scpi.close, self.control.close, self.daq.close):
            try:
                closer()
            except Exception:
                log.exception("error while closing")

    # -- threads -------------------------------------------------------------------------------------
    def _watchdog(self) -> None:
        woke = time.monotonic()
        while not self.stop_event.wait(WATCHDOG_PERIOD_S):
            now = time.monotonic()
            stalled_s, woke = max(0.0, now - woke - WATCHDOG_PERIOD_S), now     # our own lateness
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
        n = self.chunk
        p, x, sp, tab = self.params, self.plant.x, self.sp, self.tab
        fast = self.speedup <= 0.0 or self.speedup >= FAST_SPEEDUP
        batch = FRAME_BATCH_CHUNKS if fast else 1
        frames = np.empty(n * batch * ph.FRAME_BYTES, dtype=np.uint8)
        summary = np.zeros((batch, ph.N_SUMMARY))
        no_trace = np.zeros((0, ph.N_TRACE))
        rng = self.plant.rng
        noise_on = p[ph.P_NOISE] > 0.0
        zeros = np.zeros(n * batch)
        n_mean = max(1, int(math.ceil(U_REF_MEAN_SAMPLES / n)))
        ud_hist = np.zeros(n_mean)
        uq_hist = np.zeros(n_mean)
        chunks_done = 0
        out = bytearray()
        out_limit = n * batch * ph.FRAME_BYTES
        if self.speedup <= 0.0:
            self.daq.start_writer(self.stop_event)
        t0 = time.monotonic()
        plant_t0 = 0
        faults = self.faults
        while not self.stop_event.is_set():
            udc = self.supply.actual_v()
            faults.tick(self.samples / self.sample_rate_hz)
            # one chunk while a setpoint event waits (it is applied at this chunk's start, the next one
            # at the next chunk's start); a whole block otherwise
            m = 1 if (batch == 1 or self.drive.has_pending()) else batch
            self.drive.chunk_setpoints(sp, udc)
            self.load.chunk_setpoints(sp)
            k = m * n
            noise = rng.standard_normal(k) if noise_on else zeros[:k]
            scoping = self.scope.recording      # the oscilloscope wants this block's samples
            trace = np.zeros((k, ph.N_TRACE)) if scoping else no_trace
            ph.simulate(x, p, tab, sp, noise, n, self.samples, frames[:k * ph.FRAME_BYTES], summary[:m], trace)
            if scoping:
                self.scope.feed(trace)
            self.samples += k
            # publish the firmware's measurements (read by SDO)
            for row in range(max(0, m - n_mean), m):
                slot = chunks_done % n_mean
                ud_hist[slot] = summary[row, ph.Y_UD_SUM]
                uq_hist[slot] = summary[row, ph.Y_UQ_SUM]
                chunks_done += 1
            filled = min(n_mean, chunks_done) * n
            last = summary[m - 1]
            speed_rpm = float(last[ph.Y_OMEGA_SUM]) / n * RAD_S_TO_RPM
            self.drive.publish(speed_rpm, float(last[ph.Y_TORQUE_EST_SUM]) / n, udc,
                               float(ud_hist.sum()) / filled, float(uq_hist.sum()) / filled)
            self.load.publish(speed_rpm, float(last[ph.Y_LOAD_TORQUE_SUM]) / n)
            out += faults.apply_daq(frames[:k * ph.FRAME_BYTES].tobytes())
            if len(out) < out_limit and self.drive.has_pending():
                continue      # keep single event chunks together in one write
            data = bytes(out)
            out.clear()
            if self.speedup <= 0.0:
                if faults.daq_disconnected:
                    # nobody can read: no backpressure, so run in real time (frames are lost anyway)
                    self.stop_event.wait(len(data) / ph.FRAME_BYTES / self.sample_rate_hz)
                    continue
                if not self.daq.submit(data):
                    break
            else:
                self.daq.write_paced(data)
                target = t0 + (self.samples - plant_t0) / self.sample_rate_hz / self.speedup
                delay = target - time.monotonic()
                if delay > 0:
                    self.stop_event.wait(delay)
                elif delay < -1.0:   # fell behind (machine busy): do not try to catch up
                    t0 = time.monotonic()
                    plant_t0 = self.samples


def warm_up() -> None:
    """Compile (or load from numba's cache) the chunk function before the endpoints are announced."""
    sc = scn.load(scn.DEFAULT_SCENARIO)
    p, tab = scn.build(sc)
    plant = ph.Plant(p, tab)
    plant.run(ph.new_setpoints(12.0), 4)


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m plant_emulator",
                                 description="Emulated PMSM test bench: socketcand CANopen, DAQ pty, SCPI supply.")
    ap.add_argument("--scenario", default=scn.DEFAULT_SCENARIO, help="scenario name or TOML path (default paper-bench)")
    ap.add_argument("--seed", type=int, default=None, help="perturb the truth within the scenario's [seed] ranges")
    ap.add_argument("--speedup", type=float, default=1.0,
                    help="X times real time, paced like a real DAQ: what the reader does not take in time is "
                         "dropped (beyond about 5x a service on 2 cores does not keep up, and some runs fail "
                         "naming the DAQ gaps); 0 = as fast as the DAQ reader consumes, the way to run faster than real time "
                         "(default 1)")
    ap.add_argument("--can-port", type=int, default=0, help="socketcand TCP port on 127.0.0.1 (0: free port)")
    ap.add_argument("--supply-port", type=int, default=0, help="SCPI TCP port on 127.0.0.1 (0: free port)")
    ap.add_argument("--control-port", type=int, default=0,
                    help="fault control socket (JSON lines) on 127.0.0.1 (0: free port)")
    ap.add_argument("--log-level", default="WARNING", help="logging level on stderr (default WARNING)")
    ap.add_argument("--exit-on-stdin-eof", action="store_true",
                    help="stop when stdin reaches EOF: a parent holding the pipe's other end takes the emulator "
                         "with it when it dies, also by kill -9 (the kernel closes the pipe)")
    args = ap.parse_args(argv)
    if args.speedup < 0:
        ap.error("--speedup must be >= 0")
    return args


def _watch_parent_pipe(stop: threading.Event) -> None:
    """Block on stdin; EOF (or an error) means the parent is gone: stop like on SIGTERM."""
    try:
        while sys.stdin.buffer.read1(4096):
            pass
    except (OSError, ValueError):
        pass
    log.warning("stdin closed: the parent is gone; stopping")
    stop.set()


def main(argv=None) -> int:
    args = parse_args(argv)
    one_blas_thread()
    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.WARNING), stream=sys.stderr,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    stop = threading.Event()

    def on_signal(signum, frame):
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    if args.exit_on_stdin_eof:
        threading.Thread(target=_watch_parent_pipe, args=(stop,), name="parent-pipe", daemon=True).start()
    sc = scn.load(args.scenario, seed=args.seed)
    emu = Emulator(sc, speedup=args.speedup, can_port=args.can_port, supply_port=args.supply_port,
                   control_port=args.control_port)
    try:
        emu.start()
        sys.stdout.write(json.dumps(emu.endpoints()) + "\n")
        sys.stdout.flush()
        while not stop.is_set() and not emu.stop_event.is_set():
            stop.wait(0.2)
    finally:
        emu.close()
    return 0 if not emu.stop_event.is_set() or stop.is_set() else 1
