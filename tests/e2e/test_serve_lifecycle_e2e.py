"""`ripplecal serve` as a process: one Ctrl+C stops it with an SSE stream open (no traceback), and a
bench that cannot be reached at start gives one clear line while the service still comes up."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import threading
import time

import httpx
import pytest

from tests.support.operating_points import OP1
from tests.support.parent_death import die_with_parent
from tests.support.service_process import REPO, ServiceProcess, create_token, free_port

pytestmark = pytest.mark.e2e
EXIT_TIMEOUT_S = 60.0  # generous: the emulator child and the bench are shut down in order


def test_one_sigint_stops_serve_with_an_sse_stream_open(tmp_path):
    svc = ServiceProcess(tmp_path / "ripplecal.db")
    try:
        svc.wait_ready()
        got_first_event = threading.Event()

        def listen() -> None:
            # the stream must end by itself when the service shuts down (a read timeout would fail the test)
            with httpx.stream("GET", f"{svc.base}/api/v1/events", timeout=httpx.Timeout(5.0, read=EXIT_TIMEOUT_S)) as r:
                for line in r.iter_lines():
                    if line.startswith("event: bench.status"):
                        got_first_event.set()

        listener = threading.Thread(target=listen, daemon=True)
        listener.start()
        assert got_first_event.wait(30), "no bench.status on /api/v1/events"
        svc.proc.send_signal(signal.SIGINT)  # once, to the service alone (as a terminal's Ctrl+C would)
        code = svc.proc.wait(timeout=EXIT_TIMEOUT_S)
        listener.join(timeout=10)
    finally:
        svc.stop()
    log = svc.log_text()
    assert code in (0, 130), log[-3000:]  # 130: interrupted by Ctrl+C, after an orderly shutdown
    assert "Traceback" not in log and "CancelledError" not in log, log[-3000:]
    assert not listener.is_alive(), "the SSE stream did not end with the service"


def _closed_port() -> int:
    port = free_port()  # bound and released: nothing listens there
    with socket.socket() as s:
        assert s.connect_ex(("127.0.0.1", port)) != 0
    return port


def test_unreachable_bench_serve_comes_up_and_says_which_device(tmp_path):
    port = _closed_port()
    bench = tmp_path / "bench.toml"
    bench.write_text(f"""
bench_name = "bench-offline"
[can]
interface = "socketcand"
channel = "can0"
host = "127.0.0.1"
port = {port}
[daq]
url = "socket://127.0.0.1:{port}"
[supply]
url = "socket://127.0.0.1:{port}"
""")
    base_port = free_port()
    log_path = tmp_path / "service.log"
    with open(log_path, "w") as log:
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "service.cli",
                "serve",
                "--bench",
                str(bench),
                "--port",
                str(base_port),
                "--db",
                str(tmp_path / "ripplecal.db"),
            ],
            cwd=REPO,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            preexec_fn=die_with_parent(signal.SIGTERM),  # ends with pytest, even killed
        )
    base = f"http://127.0.0.1:{base_port}"
    try:
        deadline = time.monotonic() + 60
        status = None
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                status = httpx.get(f"{base}/api/v1/bench/status", timeout=2).json()
                break
            except httpx.HTTPError:
                time.sleep(0.3)
        text = log_path.read_text()
        assert status is not None, f"serve did not come up (exit {proc.poll()}):\n{text[-3000:]}"
        assert status["connected"] is False
        assert status["unreachable"]["device"] == "CAN bus"
        assert f"127.0.0.1:{port}" in status["unreachable"]["address"]
        assert f"127.0.0.1:{port}" in status["error"] and "check" in status["error"]
        # the dashboard and the stored data are served; a run is refused with the reason (409, nothing queued)
        assert httpx.get(f"{base}/", timeout=5).status_code == 200
        assert httpx.get(f"{base}/api/v1/sweeps", timeout=5).status_code == 200
        token = create_token(tmp_path / "ripplecal.db")
        r = httpx.post(
            f"{base}/api/v1/identifications",
            timeout=10,
            headers={"Authorization": f"Bearer {token}"},
            json={"operating_point": OP1, "method": "probe"},
        )
        assert r.status_code == 409 and "CAN bus" in r.json()["detail"] and "check that" in r.json()["detail"], r.text
        assert httpx.get(f"{base}/api/v1/jobs", timeout=5).json() == []
        lines = [l for l in text.splitlines() if "bench unreachable" in l]
        assert len(lines) == 1, text
        assert f"127.0.0.1:{port}" in lines[0] and "check that" in lines[0], lines[0]
        assert "Traceback" not in text and "WARNING" not in text, text
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=EXIT_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)
    assert "Traceback" not in log_path.read_text(), log_path.read_text()[-3000:]


def test_the_access_log_names_method_path_and_status_but_never_the_query(tmp_path):
    """A token a client puts in a query string must not end up in the service's log."""
    svc = ServiceProcess(tmp_path / "ripplecal.db")
    try:
        svc.wait_ready()
        r = httpx.get(f"{svc.base}/api/v1/version?token=rc_query-secret&x=1", timeout=10)
        assert r.status_code == 200, r.text
        missing = httpx.get(f"{svc.base}/api/v1/results/987654?access_token=rc_other-secret", timeout=10)
        assert missing.status_code == 404, missing.text
    finally:
        svc.stop()  # the log is complete once the process has ended
    log = svc.log_text()
    assert '"GET /api/v1/version HTTP/1.1" 200' in log, log[-3000:]
    assert '"GET /api/v1/results/987654 HTTP/1.1" 404' in log, log[-3000:]
    assert "secret" not in log and "token=" not in log, log[-3000:]


def test_a_second_serve_on_the_same_database_is_refused_naming_the_first(tmp_path):
    """The claim comes before recovery: the first service's work is untouched by the second's start."""
    db = tmp_path / "ripplecal.db"
    first = ServiceProcess(db)
    try:
        first.wait_ready()
        second = subprocess.run(
            [sys.executable, "-m", "service.cli", "serve", "--port", str(free_port()), "--db", str(db)],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert second.returncode == 2, (second.returncode, second.stderr[-3000:])
        lines = second.stderr.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in second.stderr, second.stderr
        assert f"in use by another ripplecal serve (pid {first.proc.pid}, port {first.port}" in lines[0], lines[0]
        assert httpx.get(f"{first.base}/api/v1/bench/status", timeout=5).json()["connected"]  # the first goes on
    finally:
        first.stop()
    # the claim ends with its process: a restart on the same database comes up
    again = ServiceProcess(db)
    try:
        again.wait_ready()
    finally:
        again.stop()
