"""The bench's safety limits, checked before anything is sent (also in a sweep plan's dry run).

One module, imported by the plans, the engine, the API and the bench; it needs only the settings and
the operating point, so declaring a request schema never imports the drivers.

Two kinds of check:
  - the hard limits (`check_limits`: max torque, torque sign, speed range, U_dc range): never overridden;
  - the envelope model (`check_envelope`): a point the NOMINAL motor settings predict the drive cannot hold
    (service.model.operating_point.torque_envelope: current limit, voltage limit with field weakening, the
    back-EMF above what the DC link holds) is refused up front with the reason. A machine that exceeds its
    model may be run anyway with `override_envelope_model` (an option of every request that moves the
    bench); the actuals interlock (service/bench/interlocks.py, ActualsOutsideLimits) then holds the hard limits on
    what the motor does.
`torque_tolerance_nm` is the one tolerance between a torque command and the torque a point ran at: the
model refuses a point predicted beyond it, and a result measured beyond it is never ok (`torque_departure`).
"""

from __future__ import annotations

import math

from service.errors import Invalid
from service.model.operating_point import OperatingPoint, torque_envelope
from service.settings import SafetySettings, Settings


class LimitError(Invalid, ValueError):
    """A setpoint outside the bench's safety limits (checked before anything is sent).
    `problems` pairs each operating-point field at fault with what is wrong (the API's 422 names them)."""

    kind = "value_error.bench_limits"  # the 422 item's type
    error_type = kind
    hint = ""  # what to do about it, said once per refusal

    def __init__(self, message: str, problems: tuple[tuple[str, str], ...] = ()):
        super().__init__(message)
        self.problems = problems


class EnvelopeError(LimitError):
    """A point the envelope model predicts the drive cannot hold (check_envelope); `override_envelope_model`
    lets it run, the hard limits still held on the actuals."""

    kind = "value_error.envelope"
    error_type = kind
    hint = (
        "a lower torque or speed, or a higher udc_v; override_envelope_model: true only for a machine known to "
        "exceed its nominal motor settings"
    )


def setpoint_problem(field: str, value: float, safety: SafetySettings) -> str | None:
    """What is wrong with one setpoint (`field`: torque_nm, speed_rpm or udc_v) against the hard limits (None: it
    is within them): the one statement of each limit, used for a whole operating point (check_limits) and for
    every single setpoint a run sends down (service/bench/run_commands.py)."""
    if not math.isfinite(value):  # NaN compares False with every limit below
        return f"{field} must be a finite number, got {value}"
    lim = safety
    if field == "torque_nm":
        if abs(value) > lim.max_torque_nm:
            return f"torque_nm {value:g} exceeds the limit of {lim.max_torque_nm:g} Nm"
        if lim.torque_sign == "positive" and value < 0 or lim.torque_sign == "negative" and value > 0:
            return f"torque_nm {value:g}: this bench allows {lim.torque_sign} torque only (safety.torque_sign)"
    elif field == "speed_rpm":
        if abs(value) > lim.max_speed_rpm:
            return f"speed_rpm {value:g} exceeds the limit of {lim.max_speed_rpm:g} rpm"
        if abs(value) < lim.min_speed_rpm:
            return f"speed_rpm {value:g} is below the minimum of {lim.min_speed_rpm:g} rpm (safety.min_speed_rpm)"
    elif field == "udc_v":
        if not lim.min_udc_v <= value <= lim.max_udc_v:
            return f"udc_v {value:g} outside {lim.min_udc_v:g}..{lim.max_udc_v:g} V"
    else:
        raise ValueError(f"no hard limit for {field!r}")
    return None


def check_setpoint(field: str, value: float, settings: Settings) -> None:
    """LimitError naming `field` if one setpoint is outside the hard limits (setpoint_problem)."""
    problem = setpoint_problem(field, value, settings.safety)
    if problem is not None:
        raise LimitError(problem, ((field, problem),))


def check_limits(op: OperatingPoint, settings: Settings) -> None:
    """LimitError naming every field of `op` outside the hard limits (non-finite values first: nothing else is
    judged on a NaN)."""
    fields = ("torque_nm", "speed_rpm", "udc_v")
    nonfinite = [
        (f, f"{f} must be a finite number, got {getattr(op, f)}") for f in fields if not math.isfinite(getattr(op, f))
    ]
    problems = nonfinite or [
        (f, problem) for f in fields if (problem := setpoint_problem(f, getattr(op, f), settings.safety)) is not None
    ]
    if problems:
        raise LimitError("; ".join(msg for _, msg in problems), tuple(problems))


def gamma_max_rad(requested_deg: float | None, settings: Settings) -> float:
    """The injection limit of a run (rad): what its options ask for, never above the settings' gamma_max
    (paper sec. 2.4; the bench refuses and the drive clamps anything above it)."""
    ceiling_rad = math.radians(settings.identification.gamma_max_deg)
    return ceiling_rad if requested_deg is None else min(math.radians(requested_deg), ceiling_rad)


def torque_tolerance_nm(command_nm: float, safety: SafetySettings) -> float:
    """How far a point's torque actual may be from its command, Nm: safety.torque_tolerance_fraction of |command|
    or safety.torque_tolerance_nm, whichever is wider (the drive's 0x6077 is its estimate from nominal parameters,
    and a point past its base speed reaches a little less than its command)."""
    return max(safety.torque_tolerance_fraction * abs(command_nm), safety.torque_tolerance_nm)


def torque_departure(command_nm: float, actual_nm: float | None, safety: SafetySettings) -> str | None:
    """Why a result measured at torque actual `actual_nm` is not a result at `command_nm` (None: it ran at its
    command, within torque_tolerance_nm). No reading says so too: a result must say the torque it ran at."""
    if actual_nm is None or not math.isfinite(actual_nm):
        return f"no torque actual was received during the measurement (commanded {command_nm:g} Nm)"
    tolerance = torque_tolerance_nm(command_nm, safety)
    if abs(actual_nm - command_nm) <= tolerance:
        return None
    return (
        f"the motor ran at {actual_nm:.2f} Nm (torque actual, mean over the measurement), not at its command of "
        f"{command_nm:g} Nm (tolerance +-{tolerance:.2f} Nm: safety.torque_tolerance_fraction / torque_tolerance_nm): "
        "nothing is calibrated at a point the motor does not run at"
    )


def check_envelope(op: OperatingPoint, settings: Settings) -> None:
    """Raise EnvelopeError if the envelope model (module doc) predicts the drive cannot hold `op`: its currents not
    held at all at this speed and U_dc, or its torque short of the command by more than torque_tolerance_nm.
    A point outside the hard limits is theirs to refuse (check_limits): nothing is said of it here."""
    try:
        check_limits(op, settings)
    except LimitError:
        return
    env = torque_envelope(op.speed_rpm, op.udc_v, settings.motor, settings.control.voltage_margin)
    if not env.holds_currents:
        up_to = "" if env.max_speed_rpm is None else f" (up to {env.max_speed_rpm:.0f} rpm at {op.udc_v:g} V)"
        field, msg = "speed_rpm", f"{op.label()}: the back-EMF exceeds what the DC link holds{up_to}"
        why = (
            "outside the envelope of the motor settings: the back-EMF exceeds what the DC link holds even with full "
            f"field weakening (i_d = -motor.i_max_a){up_to}; the current controller would sit in its voltage limit, "
            "the inverter's diodes rectify and the machine brake uncontrolled"
        )
    else:
        tolerance = torque_tolerance_nm(op.torque_nm, settings.safety)
        if abs(op.torque_nm) <= env.max_torque_nm + tolerance:
            return
        limit = (
            f"the current limit motor.i_max_a = {settings.motor.i_max_a:g} A"
            if env.limited_by == "current"
            else f"the voltage limit {env.u_limit_v:.2f} V (control.voltage_margin * U_dc / sqrt(3)) with field weakening"
        )
        field = "torque_nm"
        why = (
            f"outside the envelope of the motor settings: the drive holds at most {env.max_torque_nm:.2f} Nm here "
            f"({limit}), beyond the torque tolerance of {tolerance:.2f} Nm"
        )
        msg = f"{op.label()}: {why}"
    raise EnvelopeError(f"{op.label()}: {why}; {EnvelopeError.hint}", ((field, f"{msg}; {EnvelopeError.hint}"),))


def outside_envelope(op: OperatingPoint, settings: Settings, override_envelope_model: bool = False) -> str | None:
    """Why the envelope model refuses `op` (None: inside it, or the model overridden). A grid's points are judged
    one by one: a sweep or a validation runs the points inside the envelope and stores each point outside it as
    not run, with this reason, as a full-load curve clips a test bench's grid."""
    if override_envelope_model:
        return None
    try:
        check_envelope(op, settings)
    except EnvelopeError as exc:
        return f"not run: {exc}"
    return None


def check_any_inside(points: list[OperatingPoint], settings: Settings, override_envelope_model: bool = False) -> None:
    """A grid before bench work is queued (its hard limits checked apart, point by point): EnvelopeError if no
    point is inside the envelope model (nothing would run); the points outside it are not run (outside_envelope)."""
    if override_envelope_model or not points:
        return
    refused = [why for op in points if (why := outside_envelope(op, settings)) is not None]
    if len(refused) == len(points):
        raise EnvelopeError(
            f"every one of the {len(points)} point(s) is outside the envelope of the motor settings: "
            + " | ".join(w.removeprefix("not run: ") for w in refused[:3])
        )


def check_point(op: OperatingPoint, settings: Settings, override_envelope_model: bool = False) -> None:
    """Every check a point passes before bench work is queued: the hard limits (never overridden), then the
    envelope model unless `override_envelope_model`."""
    check_limits(op, settings)
    if not override_envelope_model:
        check_envelope(op, settings)
