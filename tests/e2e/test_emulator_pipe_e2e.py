"""The emulator's parent pipe (plant_emulator --exit-on-stdin-eof): an orderly stop is said, so it is not an alarm;
a parent that vanishes (EOF without the stop line: kill -9, a crash) is a warning. Both stop the emulator."""

from __future__ import annotations

import subprocess
import sys

import pytest

from service.bench.emulator_process import EmulatorProcess

pytestmark = pytest.mark.e2e


def _started(tmp_path) -> tuple[subprocess.Popen, object]:
    log = open(tmp_path / "emulator.log", "w+")
    proc = subprocess.Popen(
        [sys.executable, "-m", "plant_emulator", "--speedup", "0", "--exit-on-stdin-eof", "--log-level", "INFO"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=log,
        text=True,
        start_new_session=True,
    )
    assert proc.stdout is not None and proc.stdout.readline().startswith("{")  # its endpoints: it is up
    return proc, log


@pytest.mark.parametrize("orderly", [True, False], ids=["stop line", "parent gone"])
def test_the_emulator_stops_on_its_pipe_and_warns_only_when_the_parent_vanished(tmp_path, orderly):
    proc, log = _started(tmp_path)
    assert proc.stdin is not None
    if orderly:
        proc.stdin.write("stop\n")
        proc.stdin.flush()
    proc.stdin.close()
    assert proc.wait(timeout=20) == 0
    log.seek(0)
    text = log.read()
    if orderly:
        assert "the parent asked it to stop" in text and "WARNING" not in text, text
    else:
        assert "WARNING" in text and "without a stop: the parent is gone" in text, text


def test_the_services_emulator_stops_without_an_alarm(capfd):
    emulator = EmulatorProcess(scenario="paper-bench", speedup=0.0)
    emulator.start()
    emulator.stop()
    assert "parent is gone" not in capfd.readouterr().err
