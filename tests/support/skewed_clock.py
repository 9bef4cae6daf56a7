"""A bench PC whose clock is off, for one process and its children: libfaketime preloaded (Debian's
`faketime` package, `make faketime`), its wall clock moved by a fixed offset (FAKETIME="-30s") while time
still runs at its rate and the monotonic clock is left true, as on a PC whose clock is set wrong.
Nothing in the service is told: it reads its clock as it would on that PC.

libfaketime would fake the monotonic clock too (as the wall clock's value), and Python's timed waits
then never end (their deadline goes to the kernel unfaked); with it left true, libfaketime 0.9.10 still
garbles a monotonic clock_nanosleep (Python's time.sleep: EINVAL), so a small library preloaded before
it passes those to the kernel (monotonic_sleep.c, compiled here once)."""

from __future__ import annotations

import functools
import glob
import hashlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

LIBRARY_GLOB = "/usr/lib/*/faketime/libfaketime.so.1"
SHIM_SOURCE = Path(__file__).with_name("monotonic_sleep.c")


class FaketimeMissing(RuntimeError):
    pass


def library() -> str:
    """The libfaketime to preload; FaketimeMissing saying how to get it."""
    found = sorted(glob.glob(LIBRARY_GLOB))
    if not found:
        raise FaketimeMissing(
            f"libfaketime not found ({LIBRARY_GLOB}): `make faketime` installs Debian's faketime package"
        )
    return found[0]


@functools.cache
def monotonic_sleep_shim() -> str:
    """monotonic_sleep.c compiled (once per source: cached in the temporary directory by its hash)."""
    source = SHIM_SOURCE.read_bytes()
    target = Path(tempfile.gettempdir()) / f"ripplecal-monotonic-sleep-{hashlib.sha256(source).hexdigest()[:12]}.so"
    if target.exists():
        return str(target)
    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        raise FaketimeMissing("no C compiler (cc) for tests/support/monotonic_sleep.c: `make faketime` installs gcc")
    partial = target.with_name(f"{target.name}.{os.getpid()}.part")
    out = subprocess.run(
        [compiler, "-shared", "-fPIC", "-O2", "-o", str(partial), str(SHIM_SOURCE), "-ldl"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    if out.returncode != 0:
        raise FaketimeMissing(f"{SHIM_SOURCE.name} did not compile: {out.stderr.strip()}")
    partial.replace(target)  # whole or absent: another session may compile it at the same time
    return str(target)


def skewed_env(offset_s: int) -> dict[str, str]:
    """Environment for a process whose wall clock is `offset_s` seconds off (negative: behind)."""
    return {
        "LD_PRELOAD": f"{monotonic_sleep_shim()}:{library()}",
        "FAKETIME": f"{offset_s:+d}s",
        "FAKETIME_DONT_FAKE_MONOTONIC": "1",
    }
