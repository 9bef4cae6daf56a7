"""Paced mode (--speedup X > 0): the DAQ delivers samples at the sample rate on the wall clock, loses
nothing while its reader keeps up, and the drive applies setpoints between chunk boundaries, one
sync toggle each. Functional checks only: rates and latencies are figures of
tests/benchmarks/bench_emulator.py, never timed assertions here."""

from __future__ import annotations

import math
import time

import numpy as np
import serial

from drivers.cia402 import State402
from drivers.daq_protocol import FLAG_SYNC_INPUT, FrameDecoder
from drivers.daq_reader import DaqReader
from plant_emulator import physics as ph
from plant_emulator import scenario as scn
from plant_emulator.process import EVENT_PIECE_SAMPLES, Emulator
from tests.support.waiting import wait_until


def test_paced_mode_runs_in_real_time():
    emu = Emulator(scn.load("paper-bench"), speedup=1.0)
    emu.start()
    try:
        port = serial.Serial(emu.daq.name, timeout=0.2)
        dec = FrameDecoder()
        time.sleep(0.3)
        port.reset_input_buffer()
        t0 = time.monotonic()
        got = 0
        while time.monotonic() - t0 < 1.5:
            got += len(dec.feed(port.read(4096)))
        rate = got / (time.monotonic() - t0)
        port.close()
    finally:
        emu.close()
    assert 0.8 * 16000 <= rate <= 1.2 * 16000
    assert dec.counters.crc_failures == 0


def paced_emulator(speedup: float) -> Emulator:
    emu = Emulator(scn.load("paper-bench"), speedup=speedup)
    # generous margins on a busy machine: the DAQ's FIFO holds 5 s of stream, so only a reader that
    # stops reading for that long could see frames dropped
    emu.daq.max_pending_bytes = int(5.0 * emu.sample_rate_hz * speedup) * ph.FRAME_BYTES
    return emu


def test_a_reader_that_keeps_up_gets_every_frame():
    emu = paced_emulator(4.0)
    emu.start()
    try:
        with DaqReader(emu.daq.name) as reader:
            blocks = []
            t0 = time.monotonic()
            while time.monotonic() - t0 < 1.0:
                blocks.append(reader.read_available(1 << 16, timeout_s=5.0))
            counters = reader.counters
    finally:
        emu.close()
    index = np.concatenate([b.index for b in blocks])
    gap_before = np.concatenate([b.gap_before for b in blocks])
    assert len(index) > 4 * 16000 * 0.25  # about 4 s of plant time came; a quarter is plenty
    np.testing.assert_array_equal(np.diff(index), 1)
    assert not gap_before.any()
    assert (counters.sequence_gaps, counters.overruns, counters.samples_lost) == (0, 0, 0)
    assert emu.daq.frames_dropped == 0


def sync_toggles(flags: np.ndarray, level0: int) -> np.ndarray:
    """Indices (into flags) of the samples where the sync level differs from the one before."""
    level = (flags & FLAG_SYNC_INPUT) != 0
    before = np.concatenate([[bool(level0)], level[:-1]])
    return np.flatnonzero(level != before)


def test_setpoint_events_toggle_the_sync_flag_once_each():
    emu = paced_emulator(4.0)
    emu.start()
    drive = emu.drive
    try:
        with DaqReader(emu.daq.name) as reader:
            first = reader.read_available(1 << 16, timeout_s=5.0)
            level0 = int(first.flags[0] & FLAG_SYNC_INPUT != 0)
            # three single writes, one at a time
            for subindex, value in ((6, 1), (6, 0), (2, 0)):
                applied = drive.events_applied
                drive.write_object(0x2000, subindex, value)
                wait_until(lambda: drive.events_applied > applied, 10.0, "the event applied")
            # a burst of three queued at once (the plant thread waits for the lock meanwhile, so all
            # three are pending when it takes the first), then one more as the end marker
            with drive.lock:
                for subindex, value in ((6, 1), (8, 1), (6, 0)):
                    drive.write_object(0x2000, subindex, value)
            wait_until(lambda: drive.events_applied == 6, 10.0, "the burst applied")
            drive.write_object(0x2000, 8, 0)
            blocks = [first]
            deadline = time.monotonic() + 20.0
            while len(sync_toggles(np.concatenate([b.flags for b in blocks]), level0)) < 7:
                assert time.monotonic() < deadline, "the seventh toggle did not arrive"
                blocks.append(reader.read_available(1 << 16, timeout_s=5.0))
    finally:
        emu.close()
    index = np.concatenate([b.index for b in blocks])
    np.testing.assert_array_equal(np.diff(index), 1)
    toggles = sync_toggles(np.concatenate([b.flags for b in blocks]), level0)
    assert len(toggles) == 7 and drive.events_applied == 7, toggles  # one toggle per event
    # the burst: one event per piece start, in pieces of EVENT_PIECE_SAMPLES
    np.testing.assert_array_equal(np.diff(toggles[3:6]), EVENT_PIECE_SAMPLES)


def published_at_op1(speedup: float) -> dict[str, float]:
    """What the drive and load publish (SDO) at OP1 {2.5 Nm, 2000 rpm, 12 V} after 2 s of plant time."""
    emu = Emulator(scn.load("paper-bench"), speedup=speedup)
    ph.steady_state_init(emu.plant.x, emu.params, 2.5, 2000.0, 12.0, emu.tab)
    emu.supply.set_output(True)
    emu.drive.state = State402.OPERATION_ENABLED
    emu.load.state = State402.OPERATION_ENABLED
    emu.load.store(0x60FF, 0, 2000)
    emu.drive.torque_nm = 2.5
    emu.start()
    try:
        with DaqReader(emu.daq.name) as reader:
            got = 0
            while got < 32000:
                got += len(reader.read_available(1 << 16, timeout_s=5.0))
            d = emu.drive
            return {
                "speed_rpm": d.speed_rpm,
                "torque_nm": d.torque_actual_nm,
                "ud_ref_v": d.ud_ref_v,
                "uq_ref_v": d.uq_ref_v,
                "load_torque_nm": emu.load.torque_nm,
            }
    finally:
        emu.close()


def test_published_measurements_take_each_pieces_own_length():
    # paced pieces are a few ms (32 samples at 1x, 128 at 4x), fast ones 256-sample chunks: the speed and
    # torques (per piece) and the 0x2010 mean over 1024 periods must not depend on it
    paced, fast = published_at_op1(4.0), published_at_op1(0.0)
    assert math.isclose(paced["speed_rpm"], 2000.0, rel_tol=1e-3)
    for name, value in fast.items():
        assert math.isclose(paced[name], value, rel_tol=5e-3), (name, paced[name], value)
