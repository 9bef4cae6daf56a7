"""Connections, TLS and authentication of `ripplecal serve` (issue 25, findings 6 and 8), each through
the real process on the emulated bench.

- A flood of idle connections: with its open files limited to 256 (both limits, so it cannot raise
  them), the service takes 300 silent connections, still answers a normal request at once, closes the
  silent ones after its request-head timeout, and its log stays a few lines (the closings summarised).
  With every connection it takes in a request (event streams), a new one is answered 503, not hung.
- Plain HTTP beyond loopback is refused in one line (exit 2) without --insecure, and warned about with it.
- HTTPS on 127.0.0.1 with a self-signed certificate made here (Debian's openssl); 300 connections that
  never start their handshake do not keep it from answering, and are closed after the head timeout.
- Wrong tokens throttled per client address: after 10 the client gets 429 with Retry-After, whatever
  token it sends; another address (127.0.0.2, still loopback) with the right token is served.
"""

from __future__ import annotations

import resource
import shutil
import socket
import ssl
import subprocess
from pathlib import Path

import httpx
import pytest

from tests.support.service_process import ServiceProcess, cli, create_token
from tests.support.waiting import wait_until

pytestmark = pytest.mark.e2e

OPEN_FILES = 256
IDLE_CONNECTIONS = 300  # more than the service may open files
CAP = OPEN_FILES // 2  # the connections it takes (service/cli/connection_guard.py connection_cap)
HEAD_TIMEOUT_S = 2.0


def _limit_open_files() -> None:
    # in the child, before exec: soft and hard, so the service cannot raise them itself
    resource.setrlimit(resource.RLIMIT_NOFILE, (OPEN_FILES, OPEN_FILES))


def _settings(tmp: Path, text: str) -> Path:
    path = tmp / "settings.toml"
    path.write_text(text)
    return path


def _closed_by_peer(sock: socket.socket) -> bool:
    try:
        return sock.recv(1) == b""
    except BlockingIOError:
        return False
    except OSError:  # reset
        return True


def test_idle_connections_neither_stop_the_api_nor_flood_the_log(tmp_path):
    settings = _settings(tmp_path, f"[server]\nrequest_head_timeout_s = {HEAD_TIMEOUT_S}\n")
    svc = ServiceProcess(tmp_path / "svc.db", "--settings", str(settings), preexec_fn=_limit_open_files)
    idle: list[socket.socket] = []
    streams: list[socket.socket] = []
    try:
        svc.wait_ready()
        for _ in range(IDLE_CONNECTIONS):
            idle.append(socket.create_connection(("127.0.0.1", svc.port), timeout=10))
        # the API answers a normal request while they are open (a new one closes the longest idle)
        r = httpx.get(f"{svc.base}/api/v1/bench/status", timeout=20)
        assert r.status_code == 200 and r.json()["connected"]
        # and closes every silent one after its request-head timeout (the bound only guards a hang)
        for sock in idle:
            sock.setblocking(False)
        wait_until(lambda: all(_closed_by_peer(s) for s in idle), 60, "every idle connection closed by the service")
        assert httpx.get(f"{svc.base}/api/v1/bench/status", timeout=20).status_code == 200
        # the closings to make room: a few lines, then one summary line at the end of the 10 s window
        wait_until(lambda: "repeated" in svc.log_text(), 30, "the repeated closings summarised")
        log = svc.log_text()
        assert "Too many open files" not in log
        closings = [line for line in log.splitlines() if "closed to make room" in line]
        assert 1 <= len(closings) <= 10, closings
        assert any("repeated" in line and "times in the last 10 s" in line for line in closings), closings
        assert f"at most {CAP} connections" in log  # the cap it took, said at start
        assert len(log.splitlines()) < 150, log[-3000:]

        # every connection in a request (event streams): a new one is answered 503, and served again after
        for _ in range(CAP):
            streams.append(socket.create_connection(("127.0.0.1", svc.port), timeout=10))
            streams[-1].sendall(b"GET /api/v1/events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        for stream in streams:
            assert stream.recv(12) == b"HTTP/1.1 200"  # its response started: a request in progress
        r = httpx.get(f"{svc.base}/api/v1/bench/status", timeout=20)
        assert r.status_code == 503 and "every connection is in a request" in r.text
        for stream in streams:
            stream.close()
        wait_until(
            lambda: httpx.get(f"{svc.base}/api/v1/bench/status", timeout=20).status_code == 200,
            30,
            "the API serving again once the streams ended",
        )
    finally:
        for sock in idle + streams:
            sock.close()
        svc.stop()


def test_plain_http_beyond_loopback_is_refused_without_insecure(tmp_path):
    # refused before the database is opened or anything bound: nothing starts
    r = cli("serve", "--host", "0.0.0.0", "--port", "1", "--db", str(tmp_path / "x.db"), check=False, timeout=60)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert "in clear" in lines[0] and "--insecure" in lines[0] and "--ssl-certfile" in lines[0]
    assert not (tmp_path / "x.db").exists()


def test_insecure_says_what_it_exposes(tmp_path):
    # 192.0.2.1 (TEST-NET-1) is not an address of this machine: past the check and the warning, the bind
    # fails, so no test ever listens beyond loopback
    r = cli("serve", "--host", "192.0.2.1", "--insecure", "--port", "1", "--db", str(tmp_path / "x.db"), check=False)
    assert "warning: plain HTTP on 192.0.2.1:1" in r.stderr and "in clear" in r.stderr, r.stderr
    assert r.returncode != 0


def _self_signed(tmp: Path) -> tuple[Path, Path]:
    openssl = shutil.which("openssl")
    if openssl is None:
        pytest.fail("openssl is missing: apt-get install openssl (Debian's) to make the test certificate")
    cert, key = tmp / "cert.pem", tmp / "key.pem"
    subprocess.run(
        [openssl, "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1", "-subj", "/CN=127.0.0.1",
         "-addext", "subjectAltName=IP:127.0.0.1", "-keyout", str(key), "-out", str(cert)],
        check=True,
        capture_output=True,
        timeout=60,
    )  # fmt: skip
    return cert, key


def test_https_on_loopback_and_wrong_tokens_throttled_per_client(tmp_path):
    cert, key = _self_signed(tmp_path)
    db = tmp_path / "tls.db"
    token = create_token(db, "operator")
    settings = _settings(tmp_path, f"[server]\nrequest_head_timeout_s = {HEAD_TIMEOUT_S}\n")
    svc = ServiceProcess(
        db,
        *("--settings", str(settings), "--ssl-certfile", str(cert), "--ssl-keyfile", str(key)),
        preexec_fn=_limit_open_files,
    )
    base = f"https://127.0.0.1:{svc.port}/api/v1"
    trusted = ssl.create_default_context(cafile=str(cert))
    try:

        def ready() -> bool:
            try:
                r = httpx.get(f"{base}/bench/status", verify=trusted, timeout=5)
                return r.status_code == 200 and r.json()["connected"]
            except httpx.HTTPError:
                assert svc.proc.poll() is None, svc.log_text()[-3000:]
                return False

        wait_until(ready, 90, "the service answering over HTTPS", poll_s=0.3)
        assert f"dashboard at https://127.0.0.1:{svc.port}/" in svc.log_text()
        with pytest.raises(httpx.HTTPError):  # plain HTTP gets no answer from a TLS port
            httpx.get(f"http://127.0.0.1:{svc.port}/api/v1/bench/status", timeout=5)

        # silent connections that never start their TLS handshake (asyncio would wait 60 s for each):
        # more than the service may open files, and it answers over HTTPS again within seconds
        silent = [socket.create_connection(("127.0.0.1", svc.port), timeout=10) for _ in range(IDLE_CONNECTIONS)]
        wait_until(ready, 30, "an answer over HTTPS with the silent connections open", poll_s=0.3)
        for sock in silent:
            sock.setblocking(False)
        wait_until(lambda: all(_closed_by_peer(s) for s in silent), 60, "every silent connection closed")
        assert "Too many open files" not in svc.log_text()
        for sock in silent:
            sock.close()

        # the right token from 127.0.0.1: authenticated (no job 999: 404)
        first = httpx.Client(base_url=base, verify=trusted, timeout=10)
        operator = {"Authorization": f"Bearer {token}"}
        assert first.post("/jobs/999/cancel", headers=operator).status_code == 404
        for i in range(10):
            r = first.post("/jobs/999/cancel", headers={"Authorization": f"Bearer wrong-{i}"})
            assert r.status_code == 401, r.text
        r = first.post("/jobs/999/cancel", headers={"Authorization": "Bearer wrong-10"})
        assert r.status_code == 429, r.text
        assert 1 <= int(r.headers["Retry-After"]) <= 60 and "try again in" in r.json()["detail"]
        # throttled whatever it sends, the right token too
        assert first.post("/jobs/999/cancel", headers=operator).status_code == 429
        assert first.get("/bench/status").status_code == 200  # routes without a token are not throttled
        # another client address (127.0.0.2 is loopback too) with the right token is served
        other = httpx.Client(
            base_url=base, timeout=10, transport=httpx.HTTPTransport(local_address="127.0.0.2", verify=trusted)
        )
        assert other.post("/jobs/999/cancel", headers=operator).status_code == 404
        first.close()
        other.close()
        assert "127.0.0.1 sent 10 unknown or revoked tokens" in svc.log_text()
    finally:
        svc.stop()
