"""The bring-up check end to end (issue 29): the service on an emulated bench, mis-wired the ways a lab's bench is
(through the emulator's control socket: the angle reversed, the sync line absent, the accelerometer disconnected;
through the bench file: another node id, the DAQ's rate, the pole pairs), each named by the check with its fix;
`ripplecal bench check --emulate` passes and exits 0."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.bench_rig import Api, EmulatorRig
from tests.support.service_process import ServiceProcess

pytestmark = pytest.mark.e2e


def _failed(report: dict) -> dict[str, dict]:
    return {c["name"]: c for c in report["checks"] if not c["ok"]}


def _cli_check(tmp_path, *args: str) -> tuple[int, dict]:
    """`ripplecal bench check ARGS --json` in its own process: (exit code, the report)."""
    done = subprocess.run(
        [sys.executable, "-m", "service.cli", "bench", "check", *args, "--json", "--db", str(tmp_path / "c.db")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.stdout.strip(), done.stderr
    return done.returncode, json.loads(done.stdout)


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    directory = tmp_path_factory.mktemp("check")
    emu = EmulatorRig()
    svc = ServiceProcess(directory / "c.db", "--bench", str(emu.bench_file(directory)))
    try:
        svc.wait_ready()
        api = Api(svc, directory / "c.db")
        yield emu, api
        api.close()
    finally:
        svc.stop()
        emu.stop()


def _spin_check(api: Api) -> dict:
    r = api.post("/bench/check", {"spin": True})
    assert r.status_code == 200, r.text
    return r.json()


def test_a_bench_wired_right_passes_every_check(rig):
    emu, api = rig
    quiet = api.get("/bench/check")
    assert quiet["ok"] and not quiet["spin"], quiet
    report = _spin_check(api)
    assert report["ok"], _failed(report)
    names = [c["name"] for c in report["checks"]]
    for wanted in ("links", "drive node 5: identity", "load node 6: heartbeats", "DAQ line", "sync line", "angle"):
        assert wanted in names, names
    faults = emu.control({"status": True})["faults"]
    assert faults["drive_torque_nm"] == 0.0 and faults["drive_injection_mode"] == 0, faults


@pytest.mark.parametrize(
    ("what", "name", "fix"),
    [
        ("angle_reversed", "angle", "swap the encoder's A and B"),
        ("accel_disconnected", "accelerometer", "the accelerometer is connected"),
        ("sync_absent", "spin", "wire the drive's sync output to the DAQ's sync input"),
    ],
)
def test_each_miswiring_is_named_with_its_fix(rig, what, name, fix):
    emu, api = rig
    assert emu.control({"fault": "miswire", "what": what})["ok"]
    try:
        report = _spin_check(api)
    finally:
        assert emu.control({"fault": "miswire", "what": what, "on": False})["ok"]
    failed = _failed(report)
    assert not report["ok"] and name in failed, report["checks"]
    assert fix in failed[name]["fix"], failed[name]
    status = api.get("/bench/status")
    if status.get("drive", {}).get("state") == "fault" or status.get("interlocks", {}).get("tripped"):
        api.post("/bench/fault-reset")


def test_the_check_refuses_a_spin_without_an_operator(rig):
    _, api = rig
    assert api.http.post("/bench/check", json={"spin": True}, headers={"Authorization": ""}).status_code == 401


@pytest.mark.parametrize(
    ("line", "name", "fix"),
    [
        ("drive_node = 5", "links: drive (node 7)", "can.drive_node is its node id"),
        ("sample_rate_hz = 16000", "links: DAQ", "daq.sample_rate_hz is the rate the DAQ is set to"),
    ],
)
def test_a_bench_file_that_does_not_match_the_bench_is_named(tmp_path, line, name, fix):
    # at a real bench's clock: the emulator's DAQ streams its 16000 frames/s (at speedup 0 it runs as fast as read)
    emu = EmulatorRig(speedup=1.0)
    try:
        bench_file = emu.bench_file(tmp_path)
        text = bench_file.read_text()
        wrong = {"drive_node = 5": "drive_node = 7", "sample_rate_hz = 16000": "sample_rate_hz = 8000"}[line]
        assert line in text
        bench_file.write_text(text.replace(line, wrong))
        code, report = _cli_check(tmp_path, "--bench", str(bench_file))
        assert code == 1, report
        failed = _failed(report)
        assert name in failed and fix in failed[name]["fix"], report
    finally:
        emu.stop()


def test_wrong_pole_pairs_are_named_with_the_right_number(tmp_path):
    emu = EmulatorRig()
    try:
        bench_file = emu.bench_file(tmp_path)
        bench_file.write_text(bench_file.read_text() + "[motor]\npole_pairs = 3\n")
        code, report = _cli_check(tmp_path, "--bench", str(bench_file), "--spin")
        assert code == 1, report
        failed = _failed(report)
        text = " ".join(f"{c['detail']} {c['fix']}" for c in failed.values())
        assert "motor.pole_pairs = 4" in text, report
    finally:
        emu.stop()


def test_the_cli_check_of_the_emulated_bench_passes(tmp_path):
    code, report = _cli_check(tmp_path, "--emulate")
    assert code == 0 and report["ok"], report


def _bench_file_with(emu: EmulatorRig, directory, name: str) -> Path:
    """The emulated bench's file with one thing wrong, as a lab writes it by mistake."""
    ep = emu.endpoints
    text = emu.bench_file(directory).read_text()
    wrong = {
        "can_channel": text.replace('interface = "socketcand"', 'interface = "slcan"').replace(
            f'channel = "{ep["can"]["channel"]}"', 'channel = "/dev/ttyNOPE0"'
        ),
        "daq_regular_file": text.replace(ep["daq"], str(directory / "regular.txt")),
        "nodes_swapped": text.replace("drive_node = 5", "drive_node = 6").replace("load_node = 6", "load_node = 5"),
        # the socketcand port answers, but not SCPI: garbage to *IDN?
        "supply_garbage": text.replace(ep["supply"], f"socket://127.0.0.1:{ep['can']['port']}"),
    }[name]
    (directory / "regular.txt").write_text("not a serial port\n")
    path = directory / f"{name}.toml"
    path.write_text(wrong)
    return path


@pytest.mark.parametrize(
    ("case", "device", "fix"),
    [
        ("can_channel", "links: CAN bus", "can.interface/channel/host/port name it"),
        ("daq_regular_file", "links: DAQ", "daq.url names the DAQ's serial port"),
        ("nodes_swapped", "links: drive (node 6)", "are can.drive_node and can.load_node swapped?"),
        ("supply_garbage", "links: DC supply", "supply.url names its port"),
    ],
)
def test_a_bad_bench_file_starts_the_service_with_the_bench_unavailable_and_one_line(tmp_path, case, device, fix):
    """Issue 29 step 4: the service starts (no traceback, no exit), the bench status says unavailable, and the check
    names the device, what it found and the fix."""
    emu = EmulatorRig()
    try:
        svc = ServiceProcess(tmp_path / "b.db", "--bench", str(_bench_file_with(emu, tmp_path, case)))
        try:
            svc.wait_ready(60, connected=False)
            api = Api(svc, tmp_path / "b.db")
            try:
                status = api.wait(lambda: (s := api.get("/bench/status"))["error"] and s, 30, "the bench's error")
                assert not status["connected"] and "Traceback" not in status["error"], status
                report = api.get("/bench/check")
                assert not report["ok"] and len(report["checks"]) == 1, report
                (line,) = report["checks"]
                assert line["name"] == device and fix in line["fix"], line
            finally:
                api.close()
        finally:
            svc.stop()
    finally:
        emu.stop()
