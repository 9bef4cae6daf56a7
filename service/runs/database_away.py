"""The database away: a write waited for until the database takes it again (the bench safe meanwhile), and
the sweeps whose run waits for it, shown paused with the reason (the database cannot take that pause)."""

from __future__ import annotations

import contextlib
import logging
import threading
from typing import Callable, Iterator

from service.runs.states import SweepState
from service.store.records import SweepRecord
from service.store.storage import StorageUnavailable

log = logging.getLogger(__name__)

STORAGE_RETRY_S = (0.5, 10.0)  # first and longest pause between tries of a database that is unavailable


def durably(
    write: Callable[[], object], what: str, shutdown: threading.Event, cancel: threading.Event | None, on_worker: bool
) -> bool:
    """Call `write` until the database takes it (backoff STORAGE_RETRY_S, doubling to the last); False
    if a cancel or the shutdown ended the wait first. Only ever called with the bench safe."""
    pause = STORAGE_RETRY_S[0]
    while True:
        try:
            write()
            return True
        except StorageUnavailable as exc:
            if not on_worker:
                raise  # an API request is answered at once (503), never held
            if shutdown.is_set() or (cancel is not None and cancel.is_set()):
                log.warning("%s: given up (%s): %s", what, "shutdown" if shutdown.is_set() else "cancelled", exc)
                return False
            log.info("%s: the database is unavailable (%s); next try in %.1f s", what, exc.cause, pause)
            shutdown.wait(pause)
            pause = min(2 * pause, STORAGE_RETRY_S[1])


class StorageWaits:
    """Sweep id -> why its run waits for the database (in memory only)."""

    def __init__(self) -> None:
        self._reasons: dict[int, str] = {}

    @contextlib.contextmanager
    def waiting(self, sweep_id: int, reason: str) -> Iterator[None]:
        """While the sweep's run waits for the database (the bench safe). The database cannot take the
        pause, so it is held here: a database that can still be read (a full disk reads) shows it."""
        self._reasons[sweep_id] = reason
        try:
            yield
        finally:
            self._reasons.pop(sweep_id, None)

    def as_seen(self, sweep: SweepRecord) -> SweepRecord:
        """The sweep as stored, or paused with its reason while its run waits for the database."""
        reason = self._reasons.get(sweep["id"])
        if reason is None:
            return sweep
        return {**sweep, "state": SweepState.PAUSED.value, "pause_reason": reason}
