"""A PostgreSQL server that hangs for the service (issue 25): its postmaster stopped with SIGSTOP (no new
session can start: a connection attempt waits unanswered), then the service's backends, found in
pg_stat_activity by their application_name (a thread keeps looking, should one start all the same). This
module's own session, started before, keeps answering. `thaw()` sends SIGCONT to every process it stopped."""

from __future__ import annotations

import os
import signal
import threading

import psycopg

from tests.support.postgres import PostgresCluster

SERVICE_APPLICATION = "ripplecal"  # the service's application_name (service/store/postgres_engine.py)
LOOK_EVERY_S = 0.05


class BackendFreezer:
    def __init__(self, cluster: PostgresCluster, application_name: str = SERVICE_APPLICATION):
        self.cluster = cluster
        self.application_name = application_name
        self.frozen: set[int] = set()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._conn = psycopg.connect(
            cluster.url(), autocommit=True, connect_timeout=10, application_name="ripplecal-test-freezer"
        )

    def postmaster_pid(self) -> int:
        return int((self.cluster.data / "postmaster.pid").read_text().split()[0])

    def freeze(self) -> int:
        """Stop the postmaster, the service's backends there are now and, from a thread, any new one; how many
        backends were stopped now."""
        postmaster = self.postmaster_pid()
        os.kill(postmaster, signal.SIGSTOP)
        self.frozen.add(postmaster)
        first = self._freeze_new()
        self._thread = threading.Thread(target=self._keep_frozen, name="test-freezer", daemon=True)
        self._thread.start()
        return first

    def _freeze_new(self) -> int:
        rows = self._conn.execute(
            "SELECT pid FROM pg_stat_activity WHERE application_name = %s AND pid <> pg_backend_pid()",
            (self.application_name,),
        ).fetchall()
        new = [pid for (pid,) in rows if pid not in self.frozen]
        for pid in new:  # a backend found, then stopped: it may answer one statement in between
            try:
                os.kill(pid, signal.SIGSTOP)
                self.frozen.add(pid)
            except ProcessLookupError:
                pass
        return len(new)

    def _keep_frozen(self) -> None:
        while not self._stop.wait(LOOK_EVERY_S):
            self._freeze_new()

    def thaw(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(10)
        for pid in self.frozen:
            try:
                os.kill(pid, signal.SIGCONT)
            except ProcessLookupError:
                pass
        self.frozen.clear()
        self._conn.close()
