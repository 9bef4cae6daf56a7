"""What the browser tests share: the real service on a free loopback port with its own database (one per
module), Debian's Chromium through Playwright, a REST call with the service's operator token and the tail of the
service's log (for a failure's message)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from tests.support.parent_death import die_with_parent
from tests.support.service_process import free_port

REPO = Path(__file__).resolve().parents[2]
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-quic",
]
STARTUP_TIMEOUT_S = 60.0
STOP_GRACE_S = 10.0


def _require_browser():
    """Skip (outside CI) or fail (in CI) when the browser stack is unavailable."""
    in_ci = bool(os.environ.get("CI"))
    problems = []
    if not Path(CHROMIUM).exists():
        problems.append(f"{CHROMIUM} is absent (apt-get install chromium)")
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        problems.append("Python package playwright is not installed (pip install -e .[test])")
    if problems:
        reason = "browser test needs: " + "; ".join(problems)
        if in_ci:
            pytest.fail(reason + " — required in CI", pytrace=False)
        pytest.skip(reason)


def _log_tail(path: Path, n: int = 60) -> str:
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return "(no service log)"
    return "\n".join(lines[-n:])


def _stop(proc: subprocess.Popen) -> None:
    """SIGTERM the service; after STOP_GRACE_S kill it and whatever it left in its session."""
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=STOP_GRACE_S)
    except subprocess.TimeoutExpired:
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # the service leads its own session (start_new_session)
        except ProcessLookupError:
            pass
        proc.wait(timeout=5)


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    """The real ripplecal service on a free loopback port, with its own database."""
    _require_browser()
    tmp = tmp_path_factory.mktemp("svc")
    port = free_port()
    log_path = tmp / "service.log"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    db = tmp / "ripplecal.db"
    # an operator token in the same database, created before the service opens it
    made = subprocess.run(
        [sys.executable, "-m", "service.cli", "token", "create", "--role", "operator", "--db", str(db)],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    if made.returncode != 0 or not made.stdout.strip():
        pytest.fail(f"token create failed ({made.returncode}):\n{made.stdout}\n{made.stderr}", pytrace=False)
    operator_token = made.stdout.strip().splitlines()[-1].strip()
    cmd = [sys.executable, "-m", "service.cli", "serve", "--port", str(port), "--db", str(db)]
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(
            cmd,
            cwd=REPO,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
            preexec_fn=die_with_parent(signal.SIGTERM),  # ends with pytest, even killed
        )
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        last_err = None
        while True:
            if proc.poll() is not None:
                pytest.fail(
                    f"service exited with {proc.returncode} during start-up:\n{_log_tail(log_path)}", pytrace=False
                )
            try:
                with urllib.request.urlopen(base + "/api/v1/bench/status", timeout=2) as r:
                    if r.status == 200:
                        json.load(r)
                        break
            except (urllib.error.URLError, OSError, ValueError) as e:
                last_err = e
            if time.monotonic() > deadline:
                pytest.fail(
                    f"service not reachable on {base} within {STARTUP_TIMEOUT_S:.0f} s "
                    f"(last error: {last_err}):\n{_log_tail(log_path)}",
                    pytrace=False,
                )
            time.sleep(0.25)
        yield {"base": base, "log": log_path, "proc": proc, "token": operator_token}
    finally:
        _stop(proc)


@pytest.fixture(scope="module")
def browser(service):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


def _api(service, method: str, path: str, body: dict | None = None) -> dict:
    """A REST call with the operator token (urllib: no browser involved)."""
    req = urllib.request.Request(
        service["base"] + "/api/v1" + path,
        method=method,
        data=None if body is None else json.dumps(body).encode(),
        headers={"Authorization": f"Bearer {service['token']}", "Content-Type": "application/json"},
    )
    with urllib.request.urlopen(req, timeout=30) as r:
        return json.load(r)
