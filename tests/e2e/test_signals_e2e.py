"""Two signals in quick succession (issue 25, finding 1): SIGINT twice or SIGTERM twice, 50 ms apart, end
`ripplecal serve` within 10 s with the bench safe, idle and mid-sweep at torque (--speedup 1), and end
`make run` (its process group, as a terminal's Ctrl+C) with nothing of it left running.

The service runs against its own emulated bench (`--bench`, tests/support/bench_rig.py), so the drive's
state can be read through the emulator's control socket after the service has gone. 20 tries of each kind
are tests/benchmarks/bench_shutdown.py; the server's signal handling itself is service/cli/server.py."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import httpx
import pytest

from tests.support.parent_death import die_with_parent
from tests.support.service_process import REPO, free_port, make_run
from tests.support.signal_stop import STOP_BOUND_S, group_signal_twice, serve_try
from tests.support.waiting import wait_until

pytestmark = pytest.mark.e2e


@pytest.mark.parametrize("mid_sweep", [False, True], ids=["idle", "mid-sweep"])
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINTx2", "SIGTERMx2"])
def test_two_signals_end_serve_within_10_s_bench_safe(tmp_path, sig, mid_sweep):
    outcome = serve_try(tmp_path, sig, mid_sweep)
    assert outcome.within_bound(), f"{outcome.describe()}\n{outcome.log[-3000:]}"
    assert outcome.safe, f"{outcome.describe()}\n{outcome.log[-3000:]}"
    # an orderly end: the app's shutdown ran, quietly (SIGTERM raised again by uvicorn ends it as -15)
    assert outcome.exit_code in (130, -signal.SIGTERM), outcome.describe()
    assert "Application shutdown complete" in outcome.log, outcome.log[-3000:]
    assert "Traceback" not in outcome.log and "CancelledError" not in outcome.log, outcome.log[-3000:]
    if mid_sweep:  # the sweep it stopped says why
        assert f"service shut down ({signal.Signals(sig).name})" in outcome.log, outcome.log[-3000:]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINTx2", "SIGTERMx2"])
def test_two_signals_to_make_run_end_it_and_its_service(tmp_path, sig):
    """make passes a SIGTERM on to its child; a terminal's Ctrl+C reaches both: the service sees two."""
    stamp = tmp_path / "installed"  # the Makefile's own recipe with this venv, nothing installed
    stamp.touch()
    port = free_port()
    log_path = tmp_path / "make.log"
    with open(log_path, "w") as log:
        proc = make_run(port, _env(tmp_path), log, stamp)
    try:
        wait_until(lambda: proc.poll() is not None or _connected(port), 120, "make run serving", poll_s=0.3)
        assert proc.poll() is None, log_path.read_text()[-3000:]
        ended_s, left = group_signal_twice(proc, sig)
    finally:
        if proc.poll() is None:  # a failure above: make and its service, not left for the next tests
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
    text = log_path.read_text()
    assert ended_s is not None and ended_s <= STOP_BOUND_S, f"ended after {ended_s} s\n{text[-3000:]}"
    assert not left, f"still running after make ended: {left}\n{text[-3000:]}"
    # the service's stop ran (bench safe, its emulator stopped), and said nothing alarming
    assert "Application shutdown complete" in text, text[-3000:]
    assert "Traceback" not in text, text[-3000:]


def _env(tmp_path: Path) -> dict[str, str]:
    # the session's settings but for the database, which goes under this test's directory
    env = {k: v for k, v in os.environ.items() if not k.startswith("RIPPLECAL_") or k == "RIPPLECAL_EMULATOR__SPEEDUP"}
    return {**env, "XDG_DATA_HOME": str(tmp_path / "xdg")}


def _connected(port: int) -> bool:
    try:
        return bool(httpx.get(f"http://127.0.0.1:{port}/api/v1/bench/status", timeout=2).json().get("connected"))
    except (httpx.HTTPError, ValueError):
        return False


def test_the_backstop_ends_a_server_whose_stop_hangs(tmp_path):
    """Should the app's shutdown itself hang, a second signal still ends the process within its bound
    (service/cli/server.py: os._exit after forced_exit_s), saying so. A real uvicorn server in a child
    process whose app's shutdown never returns."""
    port = free_port()
    script = textwrap.dedent(f"""
        import contextlib, time, types
        import uvicorn
        from fastapi import FastAPI
        from service.cli.server import ServiceServer
        from service.runs.events import EventBroker

        @contextlib.asynccontextmanager
        async def lifespan(app):
            yield
            while True:  # a stop that never ends (a stuck device, a database that hangs)
                time.sleep(0.1)

        service = types.SimpleNamespace(broker=EventBroker(), shutdown_reason="")
        config = uvicorn.Config(FastAPI(lifespan=lifespan), host="127.0.0.1", port={port}, log_level="info")
        ServiceServer(config, service, forced_exit_s=1.0, unforced_exit_s=60.0).run()
    """)
    log_path = tmp_path / "server.log"
    with open(log_path, "w") as log:
        proc = subprocess.Popen(
            [sys.executable, "-c", script],
            cwd=REPO,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            preexec_fn=die_with_parent(signal.SIGKILL),
        )
    try:
        wait_until(lambda: proc.poll() is not None or _listening(port), 60, "the server listening", poll_s=0.1)
        assert proc.poll() is None, log_path.read_text()
        proc.send_signal(signal.SIGTERM)
        time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=STOP_BOUND_S)
    finally:
        if proc.poll() is None:  # a failure above: make and its service, not left for the next tests
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
    text = log_path.read_text()
    assert code == 128 + signal.SIGTERM, text
    assert "did not stop within 1 s of the second signal: exiting now, unorderly" in text, text


def _listening(port: int) -> bool:
    try:
        httpx.get(f"http://127.0.0.1:{port}/docs", timeout=1)
        return True
    except httpx.HTTPError:
        return False
