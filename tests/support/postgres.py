"""A throwaway PostgreSQL cluster for the tests: initdb into a temporary directory, started on a free
loopback port (127.0.0.1 only, its unix socket in that directory, trust authentication: nothing else
can reach it), a database per test made with CREATE DATABASE, stopped and removed at the end. The
postmaster is this process's child and ends with it, also when the test session is killed.

The server refuses to run as root: when the tests run as root (a container), its commands run as the
`postgres` OS user (initdb through runuser, the server with Popen's user=), which owns the directory.
The binaries come from `pg_config --bindir` or Debian's /usr/lib/postgresql/*/bin (`make postgresql`
installs them)."""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import signal
import socket
import subprocess
import tempfile
import time
import uuid
from pathlib import Path

from tests.support.parent_death import die_with_parent

START_TIMEOUT_S = 60  # how long the server may take to accept connections (and to stop)
# pg_ctl stop's modes as the postmaster's signals
STOP_SIGNALS = {"smart": signal.SIGTERM, "fast": signal.SIGINT, "immediate": signal.SIGQUIT}
SERVER_USER = "postgres"  # the OS user (when root) and the database superuser


class PostgresMissing(RuntimeError):
    pass


def server_bindir() -> Path:
    """The directory with initdb and postgres; PostgresMissing saying how to get them."""
    candidates = []
    if shutil.which("pg_config"):
        out = subprocess.run(["pg_config", "--bindir"], capture_output=True, text=True, timeout=10)
        if out.returncode == 0:
            candidates.append(out.stdout.strip())
    # Debian: /usr/lib/postgresql/<major>/bin, the newest first (pg_config may be libpq-dev's, without a server)
    candidates += sorted(glob.glob("/usr/lib/postgresql/*/bin"), key=lambda p: int(Path(p).parent.name), reverse=True)
    for directory in candidates:
        if (Path(directory) / "initdb").exists() and (Path(directory) / "postgres").exists():
            return Path(directory)
    raise PostgresMissing(
        "PostgreSQL server binaries (initdb, postgres) not found via pg_config --bindir or in "
        "/usr/lib/postgresql/*/bin: `make postgresql` installs Debian's postgresql package"
    )


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class PostgresCluster:
    def __init__(self, bindir: Path | None = None, durable: bool = False):
        """durable: fsync on, as a lab's server runs (benchmarks); off for tests. synchronous_commit is on
        either way (the service refuses to start on a server without it)."""
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
        self.process: subprocess.Popen | None = None  # the postmaster, while it runs

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
        """Start (again) on the same port and directory: the postmaster runs as this process's child (not
        through pg_ctl, which daemonizes it), with a parent-death signal, so it ends with the test session
        even when that is killed (tests/support/parent_death.py); returns once it accepts connections."""
        options = [
            f"listen_addresses={self.host}",
            # a test server: durability is not what is tested (a benchmark's server keeps it); but
            # synchronous_commit stays on, as the service refuses a server without it (and with fsync
            # off, waiting for the flush costs nothing)
            *([] if self.durable else ["fsync=off", "full_page_writes=off"]),
            "max_connections=200",
        ]
        argv = [str(self.bindir / "postgres"), "-D", str(self.data), "-p", str(self.port), "-k", str(self.sockets)]
        for option in options:
            argv += ["-c", option]
        user = {}
        if self.as_root:  # Popen's user= comes before the preexec: runuser would clear the parent-death signal
            pw = pwd.getpwnam(SERVER_USER)
            user = {"user": pw.pw_uid, "group": pw.pw_gid, "extra_groups": []}
        with open(self.log, "ab") as log:
            self.process = subprocess.Popen(
                argv,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,  # a Ctrl+C at the terminal reaches pytest, whose teardown stops it
                preexec_fn=die_with_parent(signal.SIGQUIT),  # immediate shutdown when pytest ends, however
                **user,
            )
        self.running = True
        try:
            self._wait_accepting(START_TIMEOUT_S)
        except BaseException:
            self.stop("immediate")
            raise

    def _wait_accepting(self, timeout_s: float) -> None:
        import psycopg

        deadline = time.monotonic() + timeout_s
        while True:
            if self.process.poll() is not None:
                raise RuntimeError(f"postgres exited with {self.process.returncode} at start:\n{self._log_tail()}")
            try:
                psycopg.connect(self.url(), connect_timeout=5).close()
                return
            except psycopg.OperationalError as exc:
                if time.monotonic() > deadline:
                    raise RuntimeError(
                        f"postgres not accepting connections within {timeout_s} s ({exc}):\n{self._log_tail()}"
                    ) from None
            time.sleep(0.1)

    def _log_tail(self) -> str:
        return self.log.read_text(errors="replace")[-2000:] if self.log.exists() else ""

    def stop(self, mode: str = "fast") -> None:
        """Stop as `pg_ctl stop -m MODE` would: smart waits for sessions, fast ends them (as a server shut
        down under the service), immediate quits at once."""
        process, self.process = self.process, None
        self.running = False
        if process is None or process.poll() is not None:
            return
        process.send_signal(STOP_SIGNALS[mode])
        try:
            process.wait(timeout=START_TIMEOUT_S)
        except subprocess.TimeoutExpired:  # its backends notice the postmaster gone and end too
            process.kill()
            process.wait(timeout=10)

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
