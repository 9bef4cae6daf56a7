"""A throwaway PostgreSQL cluster for the tests: initdb into a temporary directory, started on a free
loopback port (127.0.0.1 only, its unix socket in that directory, trust authentication: nothing else
can reach it), a database per test made with CREATE DATABASE, stopped and removed at the end.

The server refuses to run as root: when the tests run as root (a container), its commands run as the
`postgres` OS user (runuser), which owns the directory. The binaries come from `pg_config --bindir` or
Debian's /usr/lib/postgresql/*/bin (`make postgresql` installs them)."""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import uuid
from pathlib import Path

START_TIMEOUT_S = 60  # pg_ctl -w waits this long for the server to accept connections
SERVER_USER = "postgres"  # the OS user (when root) and the database superuser


class PostgresMissing(RuntimeError):
    pass


def server_bindir() -> Path:
    """The directory with initdb and pg_ctl; PostgresMissing saying how to get them."""
    candidates = []
    if shutil.which("pg_config"):
        out = subprocess.run(["pg_config", "--bindir"], capture_output=True, text=True, timeout=10)
        if out.returncode == 0:
            candidates.append(out.stdout.strip())
    # Debian: /usr/lib/postgresql/<major>/bin, the newest first (pg_config may be libpq-dev's, without a server)
    candidates += sorted(glob.glob("/usr/lib/postgresql/*/bin"), key=lambda p: int(Path(p).parent.name), reverse=True)
    for directory in candidates:
        if (Path(directory) / "initdb").exists() and (Path(directory) / "pg_ctl").exists():
            return Path(directory)
    raise PostgresMissing(
        "PostgreSQL server binaries (initdb, pg_ctl) not found via pg_config --bindir or in "
        "/usr/lib/postgresql/*/bin: `make postgresql` installs Debian's postgresql package"
    )


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class PostgresCluster:
    def __init__(self, bindir: Path | None = None, durable: bool = False):
        """durable: fsync and synchronous commit on, as a lab's server runs (benchmarks); off for tests."""
        self.bindir = bindir or server_bindir()
        self.durable = durable
        self.as_root = os.geteuid() == 0
        self.root = Path(tempfile.mkdtemp(prefix="ripplecal-pg-"))
        self.data = self.root / "data"
        self.sockets = self.root / "sockets"
        self.log = self.root / "server.log"
        self.port = _free_port()
        self.host = "127.0.0.1"
        self.running = False

    def _run(self, *argv: str, timeout_s: float = START_TIMEOUT_S + 10) -> None:
        cmd = [str(self.bindir / argv[0]), *argv[1:]]
        if self.as_root:
            cmd = ["runuser", "-u", SERVER_USER, "--", *cmd]
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
        if out.returncode != 0:
            tail = self.log.read_text()[-2000:] if self.log.exists() else ""
            raise RuntimeError(f"{' '.join(cmd)} failed ({out.returncode}): {out.stderr.strip()}\n{tail}")

    def init(self) -> "PostgresCluster":
        self.sockets.mkdir()
        if self.as_root:
            pw = pwd.getpwnam(SERVER_USER)
            for path in (self.root, self.sockets):
                os.chown(path, pw.pw_uid, pw.pw_gid)
        self._run(
            "initdb", "-D", str(self.data), "-U", SERVER_USER, "-A", "trust", "-E", "UTF8", "--locale=C", "--no-sync"
        )
        return self

    def start(self) -> None:
        """Start (again) on the same port and directory."""
        options = " ".join(
            [
                f"-c listen_addresses={self.host}",
                f"-p {self.port}",
                f"-k {self.sockets}",
                # a test server: durability is not what is tested (a benchmark's server keeps it)
                "" if self.durable else "-c fsync=off -c synchronous_commit=off -c full_page_writes=off",
                "-c max_connections=200",
            ]
        )
        self._run(
            "pg_ctl",
            "-D",
            str(self.data),
            "-l",
            str(self.log),
            "-w",
            "-t",
            str(START_TIMEOUT_S),
            "-o",
            options,
            "start",
        )
        self.running = True

    def stop(self, mode: str = "fast") -> None:
        """pg_ctl stop -m fast: sessions are ended (as a server shut down under the service)."""
        if self.running:
            self._run("pg_ctl", "-D", str(self.data), "-m", mode, "-w", "-t", str(START_TIMEOUT_S), "stop")
            self.running = False

    def url(self, dbname: str = "postgres") -> str:
        return f"postgresql://{SERVER_USER}@{self.host}:{self.port}/{dbname}"

    def create_database(self, name: str | None = None) -> str:
        """A new empty database; its URL."""
        import psycopg

        name = name or f"t_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(self.url(), autocommit=True, connect_timeout=10) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def remove(self) -> None:
        try:
            self.stop("immediate")
        finally:
            shutil.rmtree(self.root, ignore_errors=True)
