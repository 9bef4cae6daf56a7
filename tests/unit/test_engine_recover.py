"""A database with jobs a previous process left queued (killed before they ran) still starts: recover
marks them failed with the reason (found by the README test's database with earlier rows)."""

from service.runs.engine import Engine
from service.runs.events import EventBroker
from service.settings import load_settings
from service.store.storage import Storage


def test_recover_fails_jobs_left_queued(db_location):  # on SQLite and PostgreSQL (tests/conftest.py)
    storage = Storage(db_location)
    job_id = storage.create_job("identification", {"operating_point": {}, "method": "adaptive", "options": {}})
    settings = load_settings(environ={}, overrides={"server.db_path": db_location})
    Engine(storage, None, settings, EventBroker()).recover()
    job = storage.get_job(job_id)
    assert job["state"] == "failed" and "stopped while this job was queued" in job["error"]
