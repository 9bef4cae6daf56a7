"""One `ripplecal serve` per database: its claim, taken before start-up recovery touches anything.

A second service on the same database would mark the first one's running sweep `interrupted` at its
start (recovery), and both would run the same sweeps' jobs. The claim is an exclusive advisory lock
(flock) on `<database>.lock`, held for the service's life and released by the kernel when the process
ends however it ends (kill -9 included), so a stale claim never blocks a restart. The file says who
holds it (pid, port, start time), so the refusal names the holder.
"""

from __future__ import annotations

import fcntl
import json
import os
from datetime import datetime, timezone
from pathlib import Path

from service.store.errors import StorageError


class DatabaseInUse(StorageError):
    """Another service holds the database; str() names it (pid, port, since)."""


class DatabaseClaim:
    def __init__(self, db_path: str | Path, port: int | None = None):
        self.db_path = Path(db_path)
        self.path = self.db_path.with_name(self.db_path.name + ".lock")
        self.port = port
        self._fd: int | None = None

    def acquire(self) -> None:
        """Take the claim; DatabaseInUse naming the holder if another process has it."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # the lock is held on a read-only descriptor: a file held open for writing would keep the
        # database's filesystem from being remounted read-only (an operator's fix) for the service's life
        fd = os.open(self.path, os.O_RDONLY | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            raise DatabaseInUse(
                f"database {self.db_path} is in use by another ripplecal serve ({holder}): stop it "
                "first, or give this one another --db"
            ) from None
        self._fd = fd
        with open(self.path, "w") as f:  # who holds it, written while holding it
            json.dump(
                {
                    "pid": os.getpid(),
                    "port": self.port,
                    "since": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                },
                f,
            )

    def release(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
            os.close(fd)  # the lock goes with the descriptor

    def __enter__(self) -> "DatabaseClaim":
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def _holder(fd: int) -> str:
    try:
        info = json.loads(os.pread(fd, 4096, 0) or b"{}")
    except (OSError, ValueError):
        info = {}
    parts = [f"pid {info['pid']}" if info.get("pid") else "pid unknown"]
    if info.get("port"):
        parts.append(f"port {info['port']}")
    if info.get("since"):
        parts.append(f"since {info['since']}")
    return ", ".join(parts)
