"""A lab's benches as the tests read them: a bench's row in the database, and as an API lists it."""

from __future__ import annotations

import httpx

from service.store.storage import Storage


def bench_row(url: str, name: str) -> dict:
    """The bench's row in the lab's database (`url`), read with a storage of its own."""
    storage = Storage(url)
    try:
        return storage.get_bench(name)
    finally:
        storage.close()


def shown(http: httpx.Client, name: str) -> dict | None:
    """The bench as GET /benches of the service behind `http` lists it (None: not listed)."""
    return next((b for b in http.get("/benches").json() if b["name"] == name), None)
