"""Seconds of computing inside an open run at a real bench's clock (BenchRun.reading_while): a validation analyses
each run-up (a survey of 48 orders over a ramp) between its points. The emulator streams in real time here
(speedup 1), as a DAQ does: left unread for seconds, its stream overflowed the reader's queue (whole frames lost,
and the next setpoints' sync toggles with them) and the run's watchdog (3 s) tripped the interlock. Read meanwhile,
neither happens: the next point measures on a stream without an overrun, and nothing trips."""

from __future__ import annotations

import time

import pytest

from service.identification.common import measure_reference
from service.model.operating_point import OperatingPoint

pytestmark = pytest.mark.e2e
LIVE_SETTINGS = {"emulator.speedup": 1.0}  # the module's `live` (tests/conftest.py)
WORK_S = 4.0  # longer than the run's watchdog bound (3 s) and than the reader's queue holds (about 1 s)


def test_work_inside_a_run_keeps_the_daq_read_and_the_watchdog_fed(live):
    service, _, _ = live
    op = OperatingPoint(torque_nm=2.0, speed_rpm=1500, udc_v=12)
    reader = service.bench.accounting.cursor.reader
    with service.bench.run(6) as run:
        with run.operating_point(op) as session:
            measure_reference(session, 12, 64)
        overruns = reader.counters.overruns
        started = time.monotonic()
        assert run.reading_while(lambda: time.sleep(WORK_S) or 42) == 42
        assert time.monotonic() - started >= WORK_S
        with run.operating_point(op.model_copy(update={"speed_rpm": 1600.0})) as session:
            window = measure_reference(session, 12, 64)
        assert window.phasor.amplitude > 0
        assert reader.counters.overruns == overruns  # the stream was read through: no frame lost

        # the work's own error reaches the caller, and the run goes on
        def fails() -> None:
            raise ValueError("the analysis failed")

        with pytest.raises(ValueError, match="the analysis failed"):
            run.reading_while(fails)
        with run.operating_point(op) as session:
            measure_reference(session, 12, 64)
    assert not service.bench.busy and service.bench.status()["drive"]["state"] != "OPERATION_ENABLED"
