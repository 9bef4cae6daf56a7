"""A lost PostgreSQL server: its errors become StorageUnavailable("unreachable") naming
host:port/dbname (never a password), so the paths that wait for a database (the run engine's
durably(), the API's 503) work as for a locked SQLite file; once the server is back the same
Storage works again (its pool reconnects by itself)."""

from __future__ import annotations

import time

import pytest

from service.store.storage import Storage, StorageUnavailable

BACK_WITHIN_S = 60.0  # the pool's reconnection backoff after a short outage


def _with_password(url: str) -> str:
    return url.replace("postgresql://postgres@", "postgresql://postgres:s3cret-pw@")


def test_a_stopped_server_is_unavailable_and_the_same_storage_works_once_it_is_back(pg_cluster, pg_url):
    storage = Storage(_with_password(pg_url), busy_timeout_s=2.0)
    try:
        job_id = storage.create_job("identification", {"n": 1})
        pg_cluster.stop("fast")
        for call in (lambda: storage.get_job(job_id), lambda: storage.create_job("identification", {"n": 2})):
            with pytest.raises(StorageUnavailable) as exc:
                call()
            assert exc.value.cause == "unreachable"
            dbname = pg_url.rsplit("/", 1)[1]
            assert f"127.0.0.1:{pg_cluster.port}/{dbname}" in str(exc.value)
            assert "s3cret-pw" not in str(exc.value) and "s3cret-pw" not in exc.value.public
        pg_cluster.start()
        deadline = time.monotonic() + BACK_WITHIN_S
        while True:
            try:
                assert storage.get_job(job_id)["request"] == {"n": 1}
                break
            except StorageUnavailable:
                assert time.monotonic() < deadline, "the pool did not reconnect"
        assert storage.create_job("identification", {"n": 3}) > job_id
    finally:
        if not pg_cluster.running:  # a failed check above: the next tests need their server
            pg_cluster.start()
        storage.close()


def test_an_unreachable_server_at_start_is_unavailable(pg_cluster):
    url = f"postgresql://postgres:s3cret-pw@127.0.0.1:{pg_cluster.port + 1}/nowhere"  # nothing listens there
    started = time.monotonic()
    with pytest.raises(StorageUnavailable) as exc:
        Storage(url, busy_timeout_s=1.0)
    assert exc.value.cause == "unreachable" and f"127.0.0.1:{pg_cluster.port + 1}/nowhere" in str(exc.value)
    assert "s3cret-pw" not in str(exc.value)
    assert time.monotonic() - started < 10
