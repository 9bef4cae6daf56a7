"""A bench file that cannot make a whole bench leaves the devices as it found them (issue 25, finding 5).

`ripplecal serve --bench FILE` against an emulated bench in its own process (tests/support/bench_rig.py),
with a bench file wrong in one way: the DAQ path a regular file or /dev/null, the node ids swapped, a
node that is not there, the DAQ's frame rate not the one the file says. Each time: one line in the log
naming the problem and its fix, and that drive and load were left as found; the service comes up and
refuses runs with the reason; drive and load are not in FAULT, neither while it runs nor after SIGTERM
(read through the emulator's control socket, which the service never uses), and the next start with
the right file comes up with nothing tripped, no fault reset needed.
"""

from __future__ import annotations

import re
import time
from pathlib import Path

import httpx
import pytest

from service.bench.connections import LEFT_AS_FOUND
from tests.support.bench_rig import Api, EmulatorRig
from tests.support.operating_points import OP1
from tests.support.service_process import ServiceProcess
from tests.support.waiting import wait_until

pytestmark = pytest.mark.e2e

CONSUMER_HOLD_S = 2.0
"""How long after the service is gone the devices are watched: four times their 500 ms consumer time
(0x1016), so a heartbeat consumer left armed would surely have faulted by then."""


def _regular_file(emu: EmulatorRig, text: str, tmp: Path) -> str:
    daq = tmp / "daq-capture.bin"
    daq.write_bytes(b"\xa5\x5a" * 100)
    return text.replace(f'url = "{emu.endpoints["daq"]}"', f'url = "{daq}"')


def _dev_null(emu: EmulatorRig, text: str, tmp: Path) -> str:
    return text.replace(f'url = "{emu.endpoints["daq"]}"', 'url = "/dev/null"')


def _nodes_swapped(emu: EmulatorRig, text: str, tmp: Path) -> str:
    ep = emu.endpoints
    text = text.replace(f"drive_node = {ep['drive_node']}", "drive_node = LOAD")
    text = text.replace(f"load_node = {ep['load_node']}", f"load_node = {ep['drive_node']}")
    return text.replace("drive_node = LOAD", f"drive_node = {ep['load_node']}")


def _node_absent(emu: EmulatorRig, text: str, tmp: Path) -> str:
    return text.replace(f"load_node = {emu.endpoints['load_node']}", "load_node = 9")


# case -> (how the good file is spoiled, what the one line must say: the problem, then its fix)
BAD_FILES = {
    "DAQ path a regular file": (_regular_file, ["DAQ at ", "is a regular file, not a serial port", "daq.url names"]),
    "DAQ path /dev/null": (_dev_null, ["DAQ at /dev/null", "not a terminal, not a serial port", "daq.url names"]),
    "node ids swapped": (
        _nodes_swapped,
        ["drive (node 6)", "node 6 is not the drive", "are can.drive_node and can.load_node swapped?"],
    ),
    "load node absent": (_node_absent, ["load machine (node 9)", "no SDO response", "can.load_node is its node id"]),
}


@pytest.fixture(scope="module")
def emu():
    rig = EmulatorRig()
    yield rig
    rig.stop()


def _devices(emu: EmulatorRig) -> dict:
    faults = emu.control({"status": True})["faults"]
    return {
        "drive": faults["drive_state"],
        "load": faults["load_state"],
        "drive_consumer_ms": faults["drive_heartbeat_consumer_ms"],
        "load_consumer_ms": faults["load_heartbeat_consumer_ms"],
    }


def _refused_start(emu: EmulatorRig, bench: Path, db: Path) -> tuple[dict, str]:
    """serve with a bench file that cannot make a bench: it comes up, not connected; (status, the log
    once the service has ended on SIGTERM)."""
    logs = db.parent / "refused"  # its own log, kept beside the good start's
    logs.mkdir(exist_ok=True)
    svc = ServiceProcess(db, "--bench", str(bench), log_dir=logs)
    try:

        def unreachable():
            if svc.proc.poll() is not None:
                raise RuntimeError(f"serve exited with {svc.proc.returncode}: {svc.log_text()[-3000:]}")
            try:
                status = httpx.get(f"{svc.base}/api/v1/bench/status", timeout=2).json()
            except httpx.HTTPError:
                return None
            return status if status.get("unreachable") else None

        status = wait_until(unreachable, 90, "the bench refused at start", poll_s=0.3)
        assert status["connected"] is False
        api = Api(svc, db)
        r = api.post("/identifications", {"operating_point": OP1, "method": "probe"})
        api.close()
        assert r.status_code == 409 and status["unreachable"]["device"] in r.json()["detail"], r.text
        assert "fault" not in _devices(emu).values(), _devices(emu)  # nothing faulted while it runs
    finally:
        assert svc.stop() is not None
    return status, svc.log_text()


def _one_line(log: str, needles: list[str]) -> str:
    lines = [line for line in log.splitlines() if re.search(r"bench (unreachable|not as the bench file says):", line)]
    assert len(lines) == 1, log[-3000:]
    for needle in [*needles, LEFT_AS_FOUND]:
        assert needle in lines[0], (needle, lines[0])
    assert "Traceback" not in log, log[-3000:]
    return lines[0]


def _left_as_found(emu: EmulatorRig, before: dict) -> None:
    time.sleep(CONSUMER_HOLD_S)  # the service is gone: a consumer still watching it faults meanwhile
    after = _devices(emu)
    assert after == before, (before, after)
    assert "fault" not in after.values(), after


def _good_start_needs_no_reset(emu: EmulatorRig, directory: Path, db: Path) -> None:
    svc = ServiceProcess(db, "--bench", str(emu.bench_file(directory)))
    try:
        svc.wait_ready()
        status = httpx.get(f"{svc.base}/api/v1/bench/status", timeout=10).json()
        assert status["error"] is None and status["interlocks"]["tripped"] == [], status
        assert status["drive"]["state"] != "fault" and status["load"]["state"] != "fault", status
    finally:
        svc.stop()


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_a_bench_file_that_cannot_make_a_bench_leaves_the_devices_as_found(tmp_path, emu, case):
    spoil, needles = BAD_FILES[case]
    good = emu.bench_file(tmp_path)
    bad = tmp_path / "bad-bench.toml"
    bad.write_text(spoil(emu, good.read_text(), tmp_path))
    assert bad.read_text() != good.read_text()
    db = tmp_path / "ripplecal.db"
    before = _devices(emu)
    assert "fault" not in before.values(), before

    status, log = _refused_start(emu, bad, db)
    _one_line(log, needles)
    assert status["unreachable"]["left"] == LEFT_AS_FOUND and LEFT_AS_FOUND in status["error"], status
    _left_as_found(emu, before)
    _good_start_needs_no_reset(emu, tmp_path, db)


def test_after_the_bad_files_a_good_start_runs_without_a_fault_reset(tmp_path, emu):
    """The bad starts above left nothing to reset: the first run after them is measured."""
    db = tmp_path / "ripplecal.db"
    svc = ServiceProcess(db, "--bench", str(emu.bench_file(tmp_path)))
    try:
        svc.wait_ready()
        api = Api(svc, db)
        job = api.identify(OP1, method="probe")
        api.close()
        assert job["state"] == "done", job
    finally:
        svc.stop()
    # the orderly stop disarmed the consumers: the devices do not fault once the service is gone
    time.sleep(CONSUMER_HOLD_S)
    after = _devices(emu)
    assert after["drive"] != "fault" and after["load"] != "fault", after
    assert after["drive_consumer_ms"] == 0 and after["load_consumer_ms"] == 0, after


def test_a_daq_at_another_frame_rate_is_named_at_start(tmp_path):
    """The emulator streams in real time at 16000 frames/s; the bench file says 8000. Judged on the wall
    clock against the DAQ's sequence numbers, as a real DAQ streams (at --speedup 0 a stream paced by
    its reader says nothing of its rate: not judged there, see DaqReader.check_frame_rate)."""
    emu = EmulatorRig(speedup=1.0)
    try:
        rate = emu.endpoints["sample_rate_hz"]
        good = emu.bench_file(tmp_path)
        bad = tmp_path / "bad-bench.toml"
        bad.write_text(good.read_text().replace(f"sample_rate_hz = {rate}", f"sample_rate_hz = {rate // 2}"))
        assert bad.read_text() != good.read_text()
        db = tmp_path / "ripplecal.db"
        before = _devices(emu)
        status, log = _refused_start(emu, bad, db)
        line = _one_line(log, [f" frames/s, the bench file says {rate // 2}", "daq.sample_rate_hz is the rate"])
        # the rate it streams, as measured on the wall clock (rounded to 3 digits)
        streams_hz = float(re.search(r"the DAQ streams (\d+) frames/s", line)[1])
        assert abs(streams_hz / rate - 1) < 0.2, line
        assert status["unreachable"]["device"] == "DAQ", status
        _left_as_found(emu, before)
        _good_start_needs_no_reset(emu, tmp_path, db)
    finally:
        emu.stop()
