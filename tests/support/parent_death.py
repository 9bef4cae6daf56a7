"""A test's child processes end with the test session, also when it is killed (kill -9 of pytest: no
fixture teardown runs): each is started with a parent-death signal (Linux prctl PR_SET_PDEATHSIG), which
the kernel sends it when the process that started it ends, however it ends.

The signal is the child's orderly stop: SIGTERM for `ripplecal serve` (the bench left safe, its emulator
stopped), SIGQUIT for a PostgreSQL postmaster (immediate shutdown; its backends follow it). Linux clears
the setting when a process changes its user, so a server run as another user is started with Popen's
`user=` (applied before the preexec function), never through runuser or pg_ctl (a daemon: not our child).
"The process that started it" is the thread, strictly: start such children from the test's own thread,
not from a helper thread that ends before them."""

from __future__ import annotations

import ctypes
import os
import signal
import sys
from typing import Callable

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>

# resolved here, before any fork: the child between fork and exec only calls it
_prctl = ctypes.CDLL(None, use_errno=True).prctl if sys.platform.startswith("linux") else None


def die_with_parent(sig: int = signal.SIGTERM) -> Callable[[], None] | None:
    """A Popen `preexec_fn`: the child gets `sig` when this process ends. None where the kernel has no
    such thing (not Linux): the fixture's own teardown is then the only stop."""
    if _prctl is None:
        return None
    parent = os.getpid()

    def arm() -> None:
        if _prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
        if os.getppid() != parent:  # the parent ended before the setting took: the signal would never come
            os.kill(os.getpid(), sig)

    return arm
