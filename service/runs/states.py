"""The state machines of jobs and sweeps as tables (an Enum plus the transitions allowed), the errors
that end a run early, and a sweep's controls. Every state write goes through the engine's
`set_job` / `set_sweep`, which check these tables (service/runs/engine.py)."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from enum import Enum
from typing import Mapping, TypeVar

from service.errors import Conflict


class JobState(str, Enum):
    QUEUED = "queued"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"


class SweepState(str, Enum):
    QUEUED = "queued"
    RUNNING = "running"
    PAUSED = "paused"
    INTERRUPTED = "interrupted"  # the service stopped under it; resume measures what is missing
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"


J, W = JobState, SweepState
JOB_TRANSITIONS: dict[JobState, frozenset[JobState]] = {
    J.QUEUED: frozenset({J.RUNNING, J.CANCELLED, J.FAILED}),  # failed: the service stopped before it ran
    J.RUNNING: frozenset({J.DONE, J.FAILED, J.CANCELLED, J.QUEUED}),  # queued: its sweep paused (parked)
    J.DONE: frozenset(),
    J.FAILED: frozenset(),
    J.CANCELLED: frozenset(),
}
SWEEP_TRANSITIONS: dict[SweepState, frozenset[SweepState]] = {
    W.QUEUED: frozenset({W.RUNNING, W.CANCELLED, W.PAUSED, W.INTERRUPTED}),
    W.RUNNING: frozenset({W.PAUSED, W.DONE, W.FAILED, W.CANCELLED, W.INTERRUPTED}),
    W.PAUSED: frozenset({W.RUNNING, W.CANCELLED, W.QUEUED, W.INTERRUPTED}),
    W.INTERRUPTED: frozenset({W.QUEUED, W.CANCELLED}),
    W.DONE: frozenset(),
    W.FAILED: frozenset(),
    W.CANCELLED: frozenset(),
}
UNFINISHED_SWEEP_STATES = frozenset({W.QUEUED, W.RUNNING, W.PAUSED})
del J, W


class TransitionError(Conflict, RuntimeError):
    """A request that the current state does not allow (e.g. resume a finished sweep)."""


class Cancelled(Exception):
    pass


class Paused(Exception):
    """A sweep's job stops between points because its sweep pauses (the operator, an interlock): the
    job is parked (queued, out of the worker's queue) and the bench is free for other jobs until the
    sweep is resumed (service/runs/engine.py module doc)."""


State = TypeVar("State", JobState, SweepState)


def check_transition(table: Mapping[State, frozenset[State]], current: State, target: State) -> None:
    if target not in table[current]:
        raise TransitionError(f"cannot go from {current.value} to {target.value}")


@dataclass
class SweepControl:
    """A sweep's pause and cancel, set by the API's thread and read by the run between points."""

    pause: threading.Event = field(default_factory=threading.Event)
    cancel: threading.Event = field(default_factory=threading.Event)
    parked_job: int | None = None  # the sweep's job while it is paused (not in the worker's queue)
