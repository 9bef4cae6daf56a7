"""The job kinds, by the name a job stores (jobs.kind): the engine looks a kind up here, as the
identification methods (METHODS) and the export formats (EXPORT_FORMATS) are looked up. A new kind
is one module (see service/runs/kinds/host.py: JobKind) and its line below."""

from __future__ import annotations

from service.runs.kinds import identification, refinement, runup, sweep, validation
from service.runs.kinds.host import JobHost, JobKind

KINDS: dict[str, JobKind] = {
    k.name: k for k in (identification.KIND, sweep.KIND, validation.KIND, refinement.KIND, runup.KIND)
}


def kind_of(name: str) -> JobKind:
    """The kind a job names; a sweep stored before kinds were named runs as a sweep."""
    return KINDS.get(name or "sweep", KINDS["sweep"])


__all__ = ["KINDS", "JobHost", "JobKind", "kind_of"]
