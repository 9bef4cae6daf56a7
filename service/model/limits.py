"""The bench's safety limits, checked before anything is sent (also in a sweep plan's dry run).

One module, imported by the plans, the engine, the API and the bench; it needs only the settings and
the operating point, so declaring a request schema never imports the drivers.
"""

from __future__ import annotations

import math

from service.model.operating_point import OperatingPoint
from service.settings import Settings


class LimitError(ValueError):
    """A setpoint outside the bench's safety limits (checked before anything is sent).
    `problems` pairs each operating-point field at fault with what is wrong (the API's 422 names them)."""

    def __init__(self, message: str, problems: tuple[tuple[str, str], ...] = ()):
        super().__init__(message)
        self.problems = problems


def check_limits(op: OperatingPoint, settings: Settings) -> None:
    lim = settings.safety
    problems = []
    for field in ("torque_nm", "speed_rpm", "udc_v"):
        if not math.isfinite(getattr(op, field)):  # NaN compares False with every limit below
            problems.append((field, f"{field} must be a finite number, got {getattr(op, field)}"))
    if problems:
        raise LimitError("; ".join(msg for _, msg in problems), tuple(problems))
    if abs(op.torque_nm) > lim.max_torque_nm:
        problems.append(("torque_nm", f"torque_nm {op.torque_nm:g} exceeds the limit of {lim.max_torque_nm:g} Nm"))
    if lim.torque_sign == "positive" and op.torque_nm < 0 or lim.torque_sign == "negative" and op.torque_nm > 0:
        problems.append(
            (
                "torque_nm",
                f"torque_nm {op.torque_nm:g}: this bench allows {lim.torque_sign} torque only (safety.torque_sign)",
            )
        )
    if abs(op.speed_rpm) > lim.max_speed_rpm:
        problems.append(("speed_rpm", f"speed_rpm {op.speed_rpm:g} exceeds the limit of {lim.max_speed_rpm:g} rpm"))
    if abs(op.speed_rpm) < lim.min_speed_rpm:
        problems.append(
            (
                "speed_rpm",
                f"speed_rpm {op.speed_rpm:g} is below the minimum of {lim.min_speed_rpm:g} rpm (safety.min_speed_rpm)",
            )
        )
    if not lim.min_udc_v <= op.udc_v <= lim.max_udc_v:
        problems.append(("udc_v", f"udc_v {op.udc_v:g} outside {lim.min_udc_v:g}..{lim.max_udc_v:g} V"))
    if problems:
        raise LimitError("; ".join(msg for _, msg in problems), tuple(problems))


def gamma_max_rad(requested_deg: float | None, settings: Settings) -> float:
    """The injection limit of a run (rad): what its options ask for, never above the settings' gamma_max
    (paper sec. 2.4; the bench refuses and the drive clamps anything above it)."""
    ceiling_rad = math.radians(settings.identification.gamma_max_deg)
    return ceiling_rad if requested_deg is None else min(math.radians(requested_deg), ceiling_rad)
