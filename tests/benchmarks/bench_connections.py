"""A flood of idle connections against `ripplecal serve` (run: python -m tests.benchmarks.bench_connections).

Issue 25 finding 6, as reported: 1100 idle TCP connections against a service whose open files are
limited to 1024; then the API stopped answering and the log grew 65 MB in 30 s ("Too many open files"
146,557 times). Here the same flood, on plain HTTP and on HTTPS (connections that never start their TLS
handshake), against the real process on the emulated bench with both open-file limits at 1024 (it cannot
raise them), and prints:
- how long the first request made after the flood took to be answered, and the median of 20 more;
- the service's open files at their highest (sampled from /proc every 50 ms);
- how long until the service had closed every idle connection (request_head_timeout_s, default 10 s);
- what the log grew by in the 30 s from the flood on (bytes and lines).
"""

from __future__ import annotations

import os
import resource
import socket
import ssl
import statistics
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import httpx

from tests.support.service_process import ServiceProcess
from tests.support.waiting import wait_until

OPEN_FILES = 1024
CONNECTIONS = 1100
WATCH_S = 30.0


def _limit() -> None:
    resource.setrlimit(resource.RLIMIT_NOFILE, (OPEN_FILES, OPEN_FILES))


def _closed(sock: socket.socket) -> bool:
    try:
        return sock.recv(1) == b""
    except BlockingIOError:
        return False
    except OSError:
        return True


def _flood(name: str, tmp: Path, extra: tuple[str, ...], url: str, verify) -> None:
    svc = ServiceProcess(tmp / f"{name}.db", *extra, log_dir=tmp / name, preexec_fn=_limit)
    peak = [0]
    done = threading.Event()

    def watch() -> None:
        while not done.is_set():
            try:
                peak[0] = max(peak[0], len(os.listdir(f"/proc/{svc.proc.pid}/fd")))
            except OSError:
                pass
            time.sleep(0.05)

    try:
        base = url.format(port=svc.port)

        def answers() -> bool:
            try:
                return httpx.get(base, verify=verify, timeout=5).status_code == 200
            except httpx.HTTPError:
                return False

        wait_until(answers, 120, f"{name}: the service up", poll_s=0.3)
        threading.Thread(target=watch, daemon=True).start()
        log_before = Path(svc.log.name).stat().st_size
        lines_before = len(svc.log_text().splitlines())
        t0 = time.monotonic()
        idle = [socket.create_connection(("127.0.0.1", svc.port), timeout=10) for _ in range(CONNECTIONS)]
        opened_s = time.monotonic() - t0
        t1 = time.monotonic()
        wait_until(answers, 60, f"{name}: an answer with the flood open", poll_s=0.05)
        first_s = time.monotonic() - t1
        times = []
        for _ in range(20):
            t = time.perf_counter()
            assert answers()
            times.append(time.perf_counter() - t)
        for sock in idle:
            sock.setblocking(False)
        wait_until(lambda: all(_closed(s) for s in idle), 60, f"{name}: every idle connection closed")
        all_closed_s = time.monotonic() - t0
        time.sleep(max(0.0, WATCH_S - (time.monotonic() - t0)))
        grown = Path(svc.log.name).stat().st_size - log_before
        lines = len(svc.log_text().splitlines()) - lines_before
        emfile = svc.log_text().count("Too many open files")
        print(
            f"{name}: {CONNECTIONS} idle connections opened in {opened_s:.2f} s (open files {OPEN_FILES})\n"
            f"  first answer after the flood: {first_s * 1000:.0f} ms; then median {statistics.median(times) * 1000:.1f} ms"
            f" (max {max(times) * 1000:.1f} ms) over 20 requests\n"
            f"  service's open files at most: {peak[0]} of {OPEN_FILES}\n"
            f"  every idle connection closed by the service {all_closed_s:.1f} s after the flood began\n"
            f"  log in the {WATCH_S:.0f} s from the flood on: {grown:,} bytes, {lines} lines; "
            f"'Too many open files': {emfile} times",
            flush=True,
        )
        for sock in idle:
            sock.close()
    finally:
        done.set()
        svc.stop()


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        for name in ("plain", "tls"):
            (tmp / name).mkdir()
        _flood("plain", tmp, (), "http://127.0.0.1:{port}/api/v1/bench/status", True)
        cert, key = tmp / "cert.pem", tmp / "key.pem"
        subprocess.run(
            ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1", "-subj", "/CN=127.0.0.1",
             "-addext", "subjectAltName=IP:127.0.0.1", "-keyout", str(key), "-out", str(cert)],
            check=True, capture_output=True, timeout=60,
        )  # fmt: skip
        _flood(
            "tls",
            tmp,
            ("--ssl-certfile", str(cert), "--ssl-keyfile", str(key)),
            "https://127.0.0.1:{port}/api/v1/bench/status",
            ssl.create_default_context(cafile=str(cert)),
        )


if __name__ == "__main__":
    main()
