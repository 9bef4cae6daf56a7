"""A PostgreSQL session that hangs (its backend stopped with SIGSTOP: the server's kernel keeps the TCP
connection alive, so neither keepalives nor the server's statement_timeout end the wait): the call fails
as StorageUnavailable("timeout") within the client's own bound instead of holding its thread for good, and
the same Storage works again on a new session. A statement past statement_timeout on a live server is
StorageUnavailable("timeout") too."""

from __future__ import annotations

import os
import signal
import time

import pytest

from service.store.storage import Storage, StorageUnavailable

STATEMENT_TIMEOUT_S = 1.0
BOUND_S = 15.0  # the client's bound is STATEMENT_TIMEOUT_S + 1 s; wide for a loaded machine: only a hang fails


def test_a_frozen_session_is_cut_off_and_the_storage_goes_on_with_a_new_one(pg_url):
    storage = Storage(pg_url, busy_timeout_s=2.0, statement_timeout_s=STATEMENT_TIMEOUT_S)
    frozen = None
    try:
        job_id = storage.create_job("identification", {"n": 1})
        started = None
        with pytest.raises(StorageUnavailable) as exc:
            with storage.connect() as conn:
                frozen = conn.execute("SELECT pg_backend_pid()").fetchone()[0]
                os.kill(frozen, signal.SIGSTOP)  # this session hangs from here on
                started = time.monotonic()
                conn.execute("SELECT 1")
        assert time.monotonic() - started < BOUND_S
        assert exc.value.cause == "timeout" and "no answer within" in str(exc.value), exc.value
        assert storage.known_unavailable() is not None
        # the server answers: the pool's next session does the work; the frozen one is never handed out again
        assert storage.get_job(job_id)["request"] == {"n": 1}
        assert storage.known_unavailable() is None
    finally:
        if frozen is not None:
            os.kill(frozen, signal.SIGCONT)
        storage.close()


def test_a_statement_past_statement_timeout_is_unavailable_not_an_error(pg_url):
    storage = Storage(pg_url, busy_timeout_s=2.0, statement_timeout_s=STATEMENT_TIMEOUT_S)
    try:
        with pytest.raises(StorageUnavailable) as exc:
            with storage.connect() as conn:
                conn.execute("SELECT pg_sleep(?)", (STATEMENT_TIMEOUT_S * 3,))
        assert exc.value.cause == "timeout" and "statement_timeout" in str(exc.value), exc.value
    finally:
        storage.close()
