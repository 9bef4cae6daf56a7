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

from tests.support.service_process import REPO, ServiceProcess, free_port

EXIT_TIMEOUT_S = 60.0       # generous: the emulator child and the bench are shut down in order


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
        svc.proc.send_signal(signal.SIGINT)          # once, to the service alone (as a terminal's Ctrl+C would)
        code = svc.proc.wait(timeout=EXIT_TIMEOUT_S)
        listener.join(timeout=10)
    finally:
        svc.stop()
    log = svc.log_text()
    assert code in (0, 130), log[-3000:]        # 130: interrupted by Ctrl+C, after an orderly shutdown
    assert "Traceback" not in log and "CancelledError" not in log, log[-3000:]
    assert not listener.is_alive(), "the SSE stream did not end with the service"


def _closed_port() -> int:
    port = free_port()          # bound and released: nothing listens there
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
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--bench", str(bench), "--port",
                                 str(base_port), "--db", str(tmp_path / "ripplecal.db")], cwd=REPO, stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True)
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
        # the dashboard and the stored data are served; a run is refused with the reason
        assert httpx.get(f"{base}/", timeout=5).status_code == 200
        assert httpx.get(f"{base}/api/v1/sweeps", timeout=5).status_code == 200
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
