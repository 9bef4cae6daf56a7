"""The lab's PostgreSQL server goes away mid-sweep (issue 20): `ripplecal serve --bench ... --db
postgresql://...`, the server stopped (pg_ctl stop -m fast: every session ended) once the sweep has
points, started again a few seconds later. As for a locked SQLite file (test_storage_trouble_e2e.py, the
same sweep: tests/support/storage_trouble.py): the API answers 503 naming the database, the bench is made
safe, the sweep waits and goes on by itself when the server answers, every point stored exactly once."""

from __future__ import annotations

import time

import pytest

from tests.support.bench_rig import EmulatorRig
from tests.support.service_process import cli
from tests.support.storage_trouble import GRID, start, sweep_through
from tests.support.sweep_checks import results_per_point

pytestmark = pytest.mark.e2e
OUTAGE_S = 5.0  # the server stays down this long after the API has said so


@pytest.fixture(scope="module")
def emu():
    rig = EmulatorRig()
    yield rig
    rig.stop()


def test_a_lost_server_pauses_the_sweep_and_every_point_is_stored_once(emu, pg_cluster, pg_url, monkeypatch):
    svc, api = start(emu, pg_url, monkeypatch)
    causes: list[str] = []

    def server_down() -> None:
        pg_cluster.stop("fast")
        r = api.wait(lambda: (r := api.http.get("/sweeps")).status_code == 503 and r, 60, "a 503")
        causes.append(r.json()["cause"])
        assert f"127.0.0.1:{pg_cluster.port}/" in r.json()["detail"], r.text

    def server_up() -> None:
        time.sleep(OUTAGE_S)
        pg_cluster.start()

    try:
        sweep = sweep_through(api, emu, server_down, server_up)
        assert causes == ["unreachable"]
        assert set(results_per_point(pg_url, sweep["id"]).values()) == {1}
        assert len(results_per_point(pg_url, sweep["id"])) == len(GRID["torque_nm"]) * len(GRID["speed_rpm"])
        api.close()
    finally:
        if not pg_cluster.running:
            pg_cluster.start()
        svc.stop()


def test_a_command_on_a_server_that_does_not_answer_is_refused_in_one_line(pg_cluster):
    url = f"postgresql://postgres:s3cret-pw@127.0.0.1:{pg_cluster.port + 1}/lab"  # nothing listens there
    out = cli("token", "create", "--role", "viewer", "--db", url, check=False, timeout=120)
    assert out.returncode == 2, out
    [line] = out.stderr.strip().splitlines()
    assert f"database postgresql://postgres@127.0.0.1:{pg_cluster.port + 1}/lab" in line, line
    assert "cannot be reached" in line and "s3cret-pw" not in out.stderr + out.stdout, line
