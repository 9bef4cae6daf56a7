"""The CLI (issue 10, item 5): maps/sweeps listing, LUT download over the bench, identify's progress,
one database path whatever the working directory, `make run PORT= HOST=`; clear lines for bad input.

Each command runs as the installed `ripplecal` script in its own process, with its own emulator, on a
real SQLite file; the database default is steered through XDG_DATA_HOME so no test touches ~/.local.
"""

import json
import os
import re
import subprocess
import sys
import time
import zlib
from pathlib import Path

import httpx
import pytest

from service.api.public.maps import map_public
from service.maps.lut_export import lut_image
from service.store.storage import Storage
from tests.support.service_process import REPO, free_port, make_run
from tests.support.sweep_checks import holes

pytestmark = pytest.mark.e2e
RIPPLECAL = str(Path(sys.executable).parent / "ripplecal")


def _env(xdg: Path, **extra: str) -> dict[str, str]:
    # none of the session's settings but the emulator's speed (tests/conftest.py)
    env = {k: v for k, v in os.environ.items() if not k.startswith("RIPPLECAL_") or k == "RIPPLECAL_EMULATOR__SPEEDUP"}
    return {**env, "XDG_DATA_HOME": str(xdg), **extra}


def run(*args: str, env: dict, cwd: Path, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([RIPPLECAL, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def home(tmp_path_factory):
    """A per-user data dir (the default database lives under it) and two unrelated working directories."""
    root = tmp_path_factory.mktemp("cli")
    (root / "a").mkdir()
    (root / "b").mkdir()
    return root, root / "xdg" / "ripplecal" / "ripplecal.db"


def test_default_database_is_one_absolute_path_whatever_the_working_directory(home):
    root, db = home
    first = run("token", "create", "--role", "viewer", "--label", "from-a", env=_env(root / "xdg"), cwd=root / "a")
    second = run("token", "list", env=_env(root / "xdg"), cwd=root / "b")
    assert first.returncode == 0 and second.returncode == 0, first.stderr + second.stderr
    for proc in (first, second):
        assert f"ripplecal: database {db}" in proc.stderr  # printed at start, absolute
    assert "from-a" in second.stdout
    assert len(first.stdout.strip().splitlines()[-1]) >= 20  # the token still alone on the last line
    # an explicit relative path is made absolute against the working directory, once
    rel = run("token", "list", env=_env(root / "xdg", RIPPLECAL_SERVER__DB_PATH="rel.db"), cwd=root / "b")
    assert f"ripplecal: database {root / 'b' / 'rel.db'}" in rel.stderr and (root / "b" / "rel.db").exists()


def test_make_run_takes_port_and_host_and_serve_knows_a_token_made_elsewhere(home, tmp_path):
    root, db = home
    env = _env(root / "xdg")
    token = run("token", "create", "--role", "operator", env=env, cwd=root / "b").stdout.strip().splitlines()[-1]
    # the Makefile's own recipe, with this venv and a stamp that is up to date (no install)
    stamp = tmp_path / "installed"
    stamp.touch()
    port = free_port()
    log = open(tmp_path / "make.log", "w")
    proc = make_run(port, env, log, stamp)
    try:
        base = f"http://127.0.0.1:{port}/api/v1"
        deadline = time.monotonic() + 120
        while True:
            assert proc.poll() is None, (tmp_path / "make.log").read_text()
            try:
                if httpx.get(f"{base}/bench/status", timeout=2).json().get("connected"):
                    break
            except httpx.HTTPError:
                pass
            assert time.monotonic() < deadline, (tmp_path / "make.log").read_text()
            time.sleep(0.3)
        # an operator-only route: 404 (no such sweep) means the token was known, 401 would mean another database
        r = httpx.post(f"{base}/sweeps/987654/pause", headers={"Authorization": f"Bearer {token}"}, timeout=10)
        assert r.status_code == 404, r.text
    finally:
        os.killpg(proc.pid, 15)
        proc.wait(timeout=30)
        log.close()
    text = (tmp_path / "make.log").read_text()
    assert f"--host 127.0.0.1 --port {port}" in text and f"ripplecal: database {db}" in text


def test_make_run_defaults_to_loopback_8000(tmp_path):
    stamp = tmp_path / "installed"
    stamp.touch()
    out = subprocess.run(
        ["make", "-n", "--no-print-directory", "run", f"STAMP={stamp}"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=30,
        env={**os.environ, "HOST": "somehost"},
    )
    assert out.stdout.strip().splitlines()[-1].endswith("ripplecal serve --emulate --host 127.0.0.1 --port 8000"), out


def test_identify_prints_its_states_and_progress_as_they_come(home):
    root, db = home
    proc = run("identify", "--torque", "2.5", "--speed", "2000", "--json", env=_env(root / "xdg"), cwd=root / "a")
    assert proc.returncode == 0, proc.stderr[-3000:]
    err = proc.stderr
    job = re.search(r"^job (\d+): queued$", err, re.M)
    assert job, err
    n = job.group(1)
    states = re.findall(rf"^job {n}: (\w+)", err, re.M)
    assert states == ["queued", "running", "done"], err
    progress = re.findall(r"^  plant time +([\d.]+) s +residual ([\d.e+-]+) FS", err, re.M)
    assert progress, err  # at least the first window, shown while running
    running_at, done_at = err.index(f"job {n}: running"), err.index(f"job {n}: done")
    assert all(running_at < m.start() < done_at for m in re.finditer(r"^  plant time", err, re.M))
    assert '"state": "done"' in proc.stdout and "Traceback" not in err


def test_sweep_then_list_show_and_download_its_map(home):
    root, db = home
    env, cwd = _env(root / "xdg"), root / "b"
    swept = run("sweep", "--torque", "1,2.5", "--speed", "2000", "--json", env=env, cwd=cwd)
    assert swept.returncode == 0, swept.stderr[-3000:]
    out = json.loads(swept.stdout)
    sweep_id, map_id = out["sweep_id"], out["map_id"]
    assert out["state"] == "done" and map_id is not None

    listed = run("sweeps", "list", env=env, cwd=cwd)
    row = next(line.split() for line in listed.stdout.splitlines() if line.split()[:1] == [str(sweep_id)])
    assert row[1] == "sweep" and row[2] == "done" and row[4] == "2/2" and row[6] == str(map_id), listed.stdout

    shown = run("sweeps", "show", str(sweep_id), env=env, cwd=cwd)
    assert shown.returncode == 0 and f"sweep {sweep_id}: done" in shown.stdout and f"map       {map_id}" in shown.stdout
    assert len(re.findall(r"^  \S.* Nm", shown.stdout, re.M)) == 2, shown.stdout

    maps = run("maps", "list", env=env, cwd=cwd)
    row = next(line.split() for line in maps.stdout.splitlines() if line.split()[:1] == [str(map_id)])
    assert row[1] == str(sweep_id) and row[4].endswith("/2"), maps.stdout

    # the LUT goes into a drive (this command's own emulator); the CRC read back is the image's own, as
    # POST /maps/{id}/download reports it (drivers.lut_image.image_crc: CRC-32 without the CRC field)
    down = run("map", "download", str(map_id), "--json", env=env, cwd=cwd)
    not_ok = holes(map_public(Storage(db), map_id).model_dump())
    if not_ok:
        # a cell that is neither ok nor filled (rare): a map with a hole goes only with --force
        assert down.returncode != 0 and f"{not_ok} of 2 cells are not ok" in down.stderr, down.stderr[-3000:]
        down = run("map", "download", str(map_id), "--json", "--force", env=env, cwd=cwd)
    assert down.returncode == 0, down.stderr[-3000:]
    answer = json.loads(down.stdout)
    assert answer["forced"] == bool(not_ok)
    image = lut_image(map_public(Storage(db), map_id).model_dump())
    assert answer["bytes"] == len(image) and answer["cells"] == 2 and answer["map_id"] == map_id
    assert int(answer["crc32"], 16) == zlib.crc32(image[:-4])


@pytest.mark.parametrize(
    "args,needle",
    [
        (["maps", "download", "987654"], "map 987654 does not exist in "),
        (["sweeps", "show", "987654"], "sweep 987654 does not exist in "),
        (["identify", "--torque", "2.5", "--speed", "2000", "--options", "{mu"], "--options is not valid JSON"),
        (["identify", "--torque", "2.5", "--speed", "2000", "--options", "[1]"], "--options must be a JSON object"),
        (["export", "987654"], "map 987654 does not exist in "),
        # a value a model refuses, said as ours (issue 30: the library's text and URL were printed)
        (["identify", "--torque", "2.5", "--speed", "-5"], "ripplecal: speed_rpm must be greater than 0"),
    ],
)
def test_bad_input_gives_one_clear_line(home, args, needle):
    root, _ = home
    proc = run(*args, env=_env(root / "xdg"), cwd=root / "a", timeout=120)
    assert proc.returncode == 2, proc
    assert needle in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    assert "pydantic" not in proc.stderr and "Input should" not in proc.stderr, proc.stderr


def test_maps_download_refuses_an_empty_or_partial_map_before_starting_the_bench(tmp_path):
    """The API's download rules (service/runs/lut_download.py), before any bench is opened."""
    from tests.support.stored_maps import CELLS, stored_map

    db = tmp_path / "r.db"
    storage = Storage(db)
    empty, partial = stored_map(storage, failing=set(CELLS)), stored_map(storage, failing={CELLS[0]})
    # the partial map's failed cell carries a fill: a hole only when the download leaves the fill out
    for map_id, needle, extra in (
        (empty, f"map {empty} has no valid cell (0 of 4 ok)", ()),
        (partial, f"map {partial} is partial: 1 of 4 cells are not ok", ("--no-fill",)),
    ):
        proc = run(
            "maps",
            "download",
            str(map_id),
            *extra,
            "--db",
            str(db),
            env=_env(tmp_path / "xdg"),
            cwd=tmp_path,
            timeout=120,
        )
        assert proc.returncode == 2 and needle in proc.stderr, proc.stderr
        assert "starting the" not in proc.stderr and "Traceback" not in proc.stderr
    assert "--force" in proc.stderr


def test_a_bad_environment_variable_is_one_line_naming_it(tmp_path):
    proc = run(
        "token",
        "list",
        "--db",
        str(tmp_path / "r.db"),
        env=_env(tmp_path / "xdg", RIPPLECAL_SERVER__PORT="eighty"),
        cwd=tmp_path,
        timeout=120,
    )
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    [line] = proc.stderr.strip().splitlines()
    assert "server.port" in line and "(set by environment RIPPLECAL_SERVER__PORT)" in line, line


def test_identify_on_a_bench_that_cannot_be_reached_is_refused_without_a_traceback(tmp_path):
    port = free_port()  # bound and released: nothing listens there
    bench = tmp_path / "offline.toml"
    bench.write_text(
        f'[can]\ninterface = "socketcand"\nchannel = "can0"\nhost = "127.0.0.1"\nport = {port}\n'
        f'[daq]\nurl = "socket://127.0.0.1:{port}"\n[supply]\nurl = "socket://127.0.0.1:{port}"\n'
    )
    proc = run(
        "identify",
        "--torque",
        "2.5",
        "--speed",
        "2000",
        "--bench",
        str(bench),
        "--db",
        str(tmp_path / "r.db"),
        env=_env(tmp_path / "xdg"),
        cwd=tmp_path,
        timeout=120,
    )
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("ripplecal: CAN bus") and f"127.0.0.1:{port}" in last and "check that" in last, proc.stderr
    assert "job " not in proc.stderr  # refused: nothing was queued
