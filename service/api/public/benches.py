"""The lab's benches (one service per bench, all on one database), and what a queued job or sweep of
another bench waits for."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Mapping

from pydantic import BaseModel, Field

if TYPE_CHECKING:
    from service.calibration_service import CalibrationService


class BenchPublic(BaseModel):
    """A bench of the lab: one service per bench, all on one database (service/runs/lab.py)."""

    name: str
    state: str = Field(description="idle | busy | fault | disconnected | starting | stopped | unknown (never seen)")
    online: bool = Field(description="its service renewed its row within the last few seconds")
    seen: str = Field(description="online | not seen since ... | stopped since ... | never seen")
    last_seen: str | None = Field(None, description="UTC ISO 8601")
    busy: bool
    running: str | None = Field(None, description="what it runs now, e.g. sweep 12")
    queue: int = Field(description="jobs queued for it")
    software_version: str | None = None
    host: str | None = None
    port: int | None = None
    own: bool = Field(description="the bench of the service that answers")


def bench_public(row: Mapping[str, Any]) -> BenchPublic:
    return BenchPublic(**row)


def queued_waiting_for(service: CalibrationService | None, row: Mapping[str, Any]) -> str | None:
    """A queued job or sweep of another bench: what it waits for (only the running service knows the lab;
    None without one, as the CLI reads the database alone)."""
    if row["state"] != "queued" or service is None:
        return None
    return service.lab.waiting_for(row.get("bench"))
