"""Sweep plans: what to do, separate from the engine that does it (bluesky's plans / run engine).

A plan is the ordered list of operating points of a grid; `dry_run` checks every setpoint
against the bench limits before the first frame goes out.
"""
from __future__ import annotations

from dataclasses import dataclass

from pydantic import BaseModel, ConfigDict, Field, field_validator

from service.bench import LimitError, check_limits
from service.operating_point import OperatingPoint
from service.settings import Settings

MAX_GRID_POINTS = 10_000


class Grid(BaseModel):
    """Operating-point grid: torque x speed x DC-link voltage."""
    model_config = ConfigDict(extra="forbid")
    torque_nm: list[float] = Field(..., min_length=1, max_length=200)
    speed_rpm: list[float] = Field(..., min_length=1, max_length=200)
    udc_v: list[float] = Field(default_factory=lambda: [12.0], min_length=1, max_length=50)

    @field_validator("torque_nm", "speed_rpm", "udc_v")
    @classmethod
    def _sorted_unique(cls, values: list[float]) -> list[float]:
        if len(set(values)) != len(values):
            raise ValueError("values must be unique")
        return sorted(values)

    def size(self) -> int:
        return len(self.torque_nm) * len(self.speed_rpm) * len(self.udc_v)


@dataclass(frozen=True)
class SweepPlan:
    points: tuple[OperatingPoint, ...]

    @classmethod
    def from_grid(cls, grid: Grid) -> "SweepPlan":
        """U_dc outermost (the supply is slowest to change), then speed, torque innermost; the
        torque direction alternates so consecutive points differ by one torque step."""
        if grid.size() > MAX_GRID_POINTS:
            raise ValueError(f"grid has {grid.size()} points, more than {MAX_GRID_POINTS}")
        points = []
        for udc in grid.udc_v:
            for k, speed in enumerate(grid.speed_rpm):
                torques = grid.torque_nm if k % 2 == 0 else list(reversed(grid.torque_nm))
                points += [OperatingPoint(torque_nm=t, speed_rpm=speed, udc_v=udc) for t in torques]
        return cls(tuple(points))

    def dry_run(self, settings: Settings) -> None:
        """Raise LimitError naming every point that violates the bench limits; sends nothing."""
        problems = []
        for op in self.points:
            try:
                check_limits(op, settings)
            except LimitError as exc:
                problems.append(f"{op.label()}: {exc}")
        if problems:
            raise LimitError(f"{len(problems)} point(s) outside the bench limits: " + " | ".join(problems[:10]))
