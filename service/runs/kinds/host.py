"""What a job kind needs from the engine that queues and runs it, and what a kind is to the engine.

A kind (service/runs/kinds/<kind>.py) holds its submit checks, the check made when this bench takes a job
queued elsewhere, and its run body; it calls back only through `JobHost` (the engine). The engine reads
the registry (service/runs/kinds/__init__.py) and never names a kind itself.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any, Callable, Protocol

from service.runs.states import SweepControl
from service.runs.sweep_run import RunHost, SweepRunner
from service.store.recordings import RecordingStore, RunRecorder
from service.store.records import JobRecord


class JobHost(RunHost, Protocol):
    """The engine, as its job kinds see it."""

    bench_name: str
    recordings: RecordingStore | None
    sweeps: SweepRunner

    def is_own(self, bench: str | None) -> bool: ...
    def create_job(self, kind: str, request: dict[str, Any], bench: str | None, sweep_id: int | None = None) -> int: ...
    def queue_sweep(self, sweep_id: int) -> int: ...
    def publish_job(self, job_id: int) -> None: ...
    def cancel_token(self, job_id: int) -> threading.Event: ...
    def insert_runup(self, row: dict[str, Any], recorder: RunRecorder | None) -> int: ...
    def control(self, sweep_id: int) -> SweepControl: ...


@dataclass(frozen=True)
class JobKind:
    """One kind of bench work. `submit(host, ...)`: checks, stores and queues, returns the job's id;
    `check_here(host, job)`: refuses (raises) a job this bench's settings do not allow, when it takes it;
    `run(host, job_id, job)`: the body, which raises Cancelled / Paused to end early."""

    name: str
    submit: Callable[..., int]  # (host, the kind's own arguments...): each kind's signature is its own
    check_here: Callable[[JobHost, JobRecord], None]
    run: Callable[[JobHost, int, JobRecord], None]
