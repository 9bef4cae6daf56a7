"""Every operator error at start is one line and exit code 2 ("The night, second step", item 7).

Each case runs `ripplecal` as a real process (tests/support/service_process.cli): a --db that cannot be a
database, or a --bench file that cannot name a bench. stderr is one line naming the file and what is wrong,
no traceback, nothing started (the line comes before any emulator or bench is opened).
"""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

import pytest

from service.store.storage import Storage
from tests.support.service_process import cli

pytestmark = pytest.mark.e2e

COMMANDS = {
    "serve": ["serve", "--port", "1"],  # never binds: the database is refused first
    "identify": ["identify", "--torque", "2.5", "--speed", "2000"],
    "sweep": ["sweep", "--torque", "1,2.5", "--speed", "2000"],
    "token create": ["token", "create", "--role", "viewer"],
    "sweeps list": ["sweeps", "list"],
    "maps list": ["maps", "list"],
}


def _text_file(tmp: Path) -> Path:
    path = tmp / "notes.db"
    path.write_text("bench notes, not a database\n" * 20)
    return path


def _directory(tmp: Path) -> Path:
    path = tmp / "data.db"
    path.mkdir()
    return path


def _under_a_file(tmp: Path) -> Path:
    (tmp / "plain").write_text("a file where a directory should be\n")
    return tmp / "plain" / "ripplecal.db"


def _unreadable(tmp: Path) -> Path:
    path = tmp / "locked-away.db"
    Storage(path)
    path.chmod(0)
    return path


def _newer_schema(tmp: Path) -> Path:
    path = tmp / "future.db"
    Storage(path)
    with sqlite3.connect(path) as conn:
        conn.execute("PRAGMA user_version = 999")
    return path


DATABASES = {
    "text file": (_text_file, "is not a database SQLite can use (file is not a database)"),
    "directory": (_directory, "is a directory: --db must name a database file"),
    "under a file": (_under_a_file, "cannot be created: {tmp}/plain is a file, not a directory"),
    "unreadable": (_unreadable, "cannot be read and written by this user"),
    "newer schema": (_newer_schema, "is at schema 999, newer than this software"),
}


def _one_clear_line(proc, *needles: str) -> str:
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("ripplecal: "), lines[0]
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    assert proc.stdout == "", proc.stdout
    return lines[0]


@pytest.mark.parametrize("case", list(DATABASES))
@pytest.mark.parametrize("command", list(COMMANDS))
def test_a_database_that_cannot_be_used_is_one_line(tmp_path, command, case):
    make, reason = DATABASES[case]
    if case == "unreadable" and os.geteuid() == 0:
        pytest.skip("root reads and writes any file: 'under a file' is the path that cannot be opened here")
    db = make(tmp_path)
    proc = cli(*COMMANDS[command], "--db", str(db), check=False, timeout=120)
    _one_clear_line(proc, f"database {db}", reason.format(tmp=tmp_path))


BENCH_FILES = {
    "no DAQ url": ('bench_name = "rig"\n[supply]\nurl = "socket://127.0.0.1:5025"\n', "names no DAQ port ([daq] url)"),
    "no supply url": ('[daq]\nurl = "/dev/ttyUSB0"\n', "names no DC supply port ([supply] url)"),
    "invalid TOML": ('[daq\nurl = "/dev/ttyUSB0"\n', "is not valid TOML: "),
    "unknown key": (
        '[daq]\nurl = "/dev/ttyUSB0"\nbaud = 115200\n[supply]\nurl = "socket://127.0.0.1:5025"\n',
        "daq.baud: unknown key",
    ),
}


@pytest.mark.parametrize("case", list(BENCH_FILES))
@pytest.mark.parametrize("command", ["serve", "identify", "sweep"])
def test_a_bench_file_that_names_no_bench_is_one_line(tmp_path, command, case):
    text, reason = BENCH_FILES[case]
    bench = tmp_path / "rig.toml"
    bench.write_text(text)
    db = tmp_path / "ripplecal.db"
    proc = cli(*COMMANDS[command], "--bench", str(bench), "--db", str(db), check=False, timeout=120)
    _one_clear_line(proc, str(bench), reason)
    assert not db.exists()  # refused before the database is opened
