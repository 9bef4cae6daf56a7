"""Paced mode (--speedup 1): the DAQ delivers samples at the sample rate on the wall clock."""
from __future__ import annotations

import time

import serial

from drivers.daq_protocol import FrameDecoder
from plant_emulator import scenario as scn
from plant_emulator.process import Emulator


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
