"""A test session killed with kill -9 (no teardown runs) leaves nothing running (issue 25): its throwaway
PostgreSQL cluster, the services it started and their emulators, and its own emulated benches end by
themselves (tests/support/parent_death.py, tests/support/postgres.py, tests/support/service_process.py,
tests/support/bench_rig.py). Proven on a pytest of its own that uses those fixtures, killed mid-test."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from tests.support.parent_death import die_with_parent
from tests.support.service_process import REPO
from tests.support.signal_stop import left_running
from tests.support.waiting import wait_until

pytestmark = pytest.mark.e2e
GONE_WITHIN_S = 30.0  # the service's orderly stop (bench safe) is the slowest; it takes a second or two

HOLDING_TEST = """
    import json, os, time
    from tests.support.bench_rig import EmulatorRig, children_of
    from tests.support.service_process import ServiceProcess

    def test_holds_everything(pg_cluster, pg_url, tmp_path):
        rig = EmulatorRig()
        svc = ServiceProcess(pg_url, "--emulate", log_dir=tmp_path)
        svc.wait_ready()
        postmaster = pg_cluster.process.pid
        pids = {
            "postmaster": [postmaster],
            "postgres backends": children_of(postmaster),
            "service": [svc.proc.pid],
            "service's emulator": children_of(svc.proc.pid),
            "emulated bench": [rig.proc.pid],
        }
        tmp = os.environ["PIDS_FILE"] + ".tmp"
        with open(tmp, "w") as f:
            json.dump(pids, f)
        os.rename(tmp, os.environ["PIDS_FILE"])
        time.sleep(600)  # killed here
"""


def test_a_killed_session_leaves_no_cluster_service_or_emulator_running(tmp_path):
    test_file = tmp_path / "test_holding.py"
    test_file.write_text(textwrap.dedent(HOLDING_TEST))
    pids_file = tmp_path / "pids.json"
    log_path = tmp_path / "pytest.log"
    with open(log_path, "w") as log:
        session = subprocess.Popen(
            [sys.executable, "-m", "pytest", "-p", "tests.conftest", "-p", "no:cacheprovider", "-q", str(test_file)],
            cwd=REPO,
            env={**os.environ, "PIDS_FILE": str(pids_file)},
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            preexec_fn=die_with_parent(signal.SIGKILL),  # this test killed: the one it runs too
        )
    try:
        wait_until(lambda: session.poll() is not None or pids_file.exists(), 180, "the session holding its fixtures")
        assert session.poll() is None, log_path.read_text()[-3000:]
        pids = json.loads(pids_file.read_text())
        assert all(pids.values()), pids  # each kind was found running
        os.kill(session.pid, signal.SIGKILL)
        session.wait(10)
        killed_at = time.monotonic()
        everything = [pid for group in pids.values() for pid in group]
        left = left_running(everything, GONE_WITHIN_S)
        gone_s = time.monotonic() - killed_at
    finally:
        if session.poll() is None:
            session.kill()
            session.wait(10)
    named = {name: [p for p in group if p in left] for name, group in pids.items()}
    for pid in left:  # the failure is reported; the rest of the suite must not run beside them
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    assert not left, f"still running {gone_s:.1f} s after kill -9 of pytest: {named}"
