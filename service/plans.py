"""Sweep plans: what to do, separate from the engine that does it (bluesky's plans / run engine).

A plan is the ordered list of operating points of a grid; `dry_run` checks every setpoint
against the bench limits before the first frame goes out.
"""
from __future__ import annotations

from dataclasses import dataclass

from pydantic import BaseModel, ConfigDict, Field, FiniteFloat, field_validator

from service.limits import LimitError, check_limits
from service.operating_point import OperatingPoint
from service.settings import SafetySettings, Settings

MAX_GRID_POINTS = 10_000


class Grid(BaseModel):
    """Operating-point grid: torque x speed x DC-link voltage."""
    model_config = ConfigDict(extra="forbid")
    torque_nm: list[FiniteFloat] = Field(..., min_length=1, max_length=200, description="torque commands T* in Nm")
    speed_rpm: list[FiniteFloat] = Field(..., min_length=1, max_length=200, description="mechanical speeds in rpm")
    udc_v: list[FiniteFloat] = Field(default_factory=lambda: [12.0], min_length=1, max_length=50,
                                     description="DC-link voltages in V")

    @field_validator("torque_nm", "speed_rpm", "udc_v")
    @classmethod
    def _sorted_unique(cls, values: list[float]) -> list[float]:
        if len(set(values)) != len(values):
            raise ValueError("values must be unique")
        return sorted(values)

    def size(self) -> int:
        return len(self.torque_nm) * len(self.speed_rpm) * len(self.udc_v)


class SweepTooLarge(ValueError):
    """A grid above `safety.max_sweep_points_unconfirmed` sent without `confirm_large`."""


def check_sweep_size(grid: Grid, confirm_large: bool, safety: SafetySettings) -> None:
    """A sweep that runs for hours is started on purpose: above the configured size it needs the flag."""
    if grid.size() > MAX_GRID_POINTS:
        raise ValueError(f"grid has {grid.size()} points, more than the maximum of {MAX_GRID_POINTS}")
    if grid.size() > safety.max_sweep_points_unconfirmed and not confirm_large:
        raise SweepTooLarge(
            f"grid has {grid.size()} points, more than {safety.max_sweep_points_unconfirmed} "
            f"(safety.max_sweep_points_unconfirmed): send \"confirm_large\": true to run it")


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
        problems, fields = [], {}
        for op in self.points:
            try:
                check_limits(op, settings)
            except LimitError as exc:
                problems.append(f"{op.label()}: {exc}")
                for field, msg in exc.problems:
                    fields.setdefault(field, []).append(f"{op.label()}: {msg}")
        if problems:
            # one entry per grid field, the first few points named (a 400-point grid would flood the answer)
            per_field = tuple((f, f"{len(m)} point(s): " + " | ".join(m[:5])) for f, m in fields.items())
            raise LimitError(f"{len(problems)} point(s) outside the bench limits: " + " | ".join(problems[:10]),
                             per_field)
