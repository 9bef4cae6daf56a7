"""Run `ripplecal serve` (which starts plant_emulator as its child) for end-to-end tests."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

from tests.support.parent_death import die_with_parent

REPO = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cli(*args: str, check: bool = True, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "service.cli", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=check,
    )


def create_token(db: Path, role: str = "operator") -> str:
    return cli("token", "create", "--role", role, "--db", str(db)).stdout.strip().splitlines()[-1]


def _stopped_with_pytest(preexec_fn=None):
    """The child's preexec: SIGTERM (its orderly stop, bench safe) when this process ends, even by kill -9
    (tests/support/parent_death.py), then the test's own `preexec_fn`."""
    arm = die_with_parent(signal.SIGTERM)

    def preexec() -> None:
        if arm is not None:
            arm()
        if preexec_fn is not None:
            preexec_fn()

    return preexec


def make_run(port: int, env: dict[str, str], log, stamp: Path) -> subprocess.Popen:
    """`make run PORT= HOST=127.0.0.1` (the Makefile's own recipe) with this venv and `stamp` as its
    up-to-date install stamp (nothing installed), in a process group of its own (signal it with killpg,
    as a terminal's Ctrl+C reaches make and its service both); stdout and stderr to `log`. make passes a
    SIGTERM on to its service: both end with pytest, even when that is killed."""
    return subprocess.Popen(
        [
            "make",
            "--no-print-directory",
            "run",
            f"PORT={port}",
            "HOST=127.0.0.1",
            f"VENV={Path(sys.executable).parent.parent}",
            f"STAMP={stamp}",
        ],
        cwd=REPO,
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        preexec_fn=die_with_parent(signal.SIGTERM),
    )


class ServiceProcess:
    def __init__(
        self,
        db: Path,
        *extra: str,
        log_dir: Path | None = None,
        env: dict[str, str] | None = None,
        preexec_fn=None,
    ):
        """`log_dir`: where service.log goes (default: beside the database); `env`: variables added to
        this process's environment (e.g. a skewed clock, tests/support/skewed_clock.py); `preexec_fn`: run
        in the child before it starts (e.g. a lower open-file limit, tests/e2e/test_connections_e2e.py)."""
        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        self.log = open((log_dir or db.parent) / "service.log", "w")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "service.cli", "serve", "--port", str(self.port), "--db", str(db), *extra],
            cwd=REPO,
            stdout=self.log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env={**os.environ, **env} if env else None,
            preexec_fn=_stopped_with_pytest(preexec_fn),
        )

    def wait_ready(self, timeout_s: float = 90.0, connected: bool = True) -> None:
        """Until the service answers with its bench connected (`connected` False: answering at all, the bench
        maybe unreachable)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"service exited with {self.proc.returncode}: {self.log_text()[-3000:]}")
            try:
                r = httpx.get(f"{self.base}/api/v1/bench/status", timeout=2)
                if r.status_code == 200 and (r.json().get("connected") or not connected):
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.3)
        raise TimeoutError(f"service not ready in {timeout_s} s: {self.log_text()[-3000:]}")

    def log_text(self) -> str:
        if not self.log.closed:
            self.log.flush()
        return Path(self.log.name).read_text()

    def stop(self) -> int | None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(timeout=10)
        self.log.close()
        return self.proc.returncode
