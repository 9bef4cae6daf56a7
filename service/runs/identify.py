"""One identification at one operating point: go there, run the method, leave the bench safe."""

from __future__ import annotations

import threading
from typing import Any, Callable, Protocol, Sequence, TypedDict, cast

from service.bench.bench import Bench
from service.bench.run import BenchRun
from service.errors import Invalid
from service.identification import METHODS, IdentificationResult
from service.identification.common import Conditions, MethodOptions, Prior
from service.identification.session import MeasurementError, Window
from service.model.limits import gamma_max_rad, torque_departure
from service.model.operating_point import OperatingPoint
from service.model.secondary_path import model_secondary_path
from service.settings import Settings
from service.store.recordings import RunRecorder


def parse_options(method: str, options: dict[str, Any] | None) -> MethodOptions:
    """Validated options model for `method` (raises ValueError / pydantic ValidationError)."""
    if method not in METHODS:
        raise ValueError(f"method {method!r} is not available; choose one of {sorted(METHODS)}")
    # every method's options model is a MethodOptions (the registry types it as type[BaseModel])
    return cast(MethodOptions, METHODS[method].options_model.model_validate(options or {}))


class _PlantTimeBounded(Protocol):
    def plant_time_bound_s(self, harmonic_frequency_hz: float) -> float: ...


def plant_time_bound_s(options: MethodOptions, harmonic_frequency_hz: float) -> float:
    """The worst-case plant time of one point under these options, s. Every method's options define the
    bound (service/identification/<method>.py); their base MethodOptions does not declare it."""
    return cast(_PlantTimeBounded, options).plant_time_bound_s(harmonic_frequency_hz)


class PlantTimeError(Invalid, ValueError):
    """A method's options would ask for more plant time at one point than the bench allows."""

    at = "options"
    error_type = "value_error.plant_time"


def check_plant_time(speeds_rpm: Sequence[float], method: str, options: MethodOptions, settings: Settings) -> None:
    """Refuse (before queueing) options whose worst case exceeds safety.max_plant_s_per_point at the
    slowest speed asked for (a harmonic period is longest there)."""
    h, pole_pairs = settings.identification.harmonic_order, settings.motor.pole_pairs
    slowest_hz = min(abs(n) for n in speeds_rpm) / 60.0 * pole_pairs * h
    bound_s = plant_time_bound_s(options, slowest_hz)
    limit_s = settings.safety.max_plant_s_per_point
    if bound_s > limit_s:
        raise PlantTimeError(
            f"{method} options may take up to {bound_s:.0f} s of plant time per operating point "
            f"(at {min(speeds_rpm):g} rpm), more than safety.max_plant_s_per_point = {limit_s:g} s: "
            "choose fewer grid points, shorter windows or fewer steps"
        )


class RunSettings(TypedDict):
    """The keywords of Bench.run a method's options decide."""

    harmonic_order: int
    gamma_max_rad: float
    decoupling: bool


def run_settings(settings: Settings, options: MethodOptions) -> RunSettings:
    """What a bench run needs from a method's options: harmonic order, gamma_max, drive decoupling."""
    ident = settings.identification
    return {
        "harmonic_order": ident.harmonic_order,
        "gamma_max_rad": gamma_max_rad(options.gamma_max_deg, settings),
        "decoupling": ident.decoupling if options.decoupling is None else options.decoupling,
    }


def identify_at(
    bench: Bench,
    settings: Settings,
    op: OperatingPoint,
    method: str,
    options: MethodOptions,
    prior: Prior | None = None,
    cancel: threading.Event | None = None,
    progress: Callable[[Window], None] | None = None,
    recorder: RunRecorder | None = None,
) -> IdentificationResult:
    """One identification as a run of its own: go to `op`, run `method`, leave the bench safe (see
    identify_in_run). `cancel` is the run's cancel token: set, the run stops at its next DAQ read."""
    with bench.run(cancel=cancel, **run_settings(settings, options)) as run:
        result = identify_in_run(run, settings, op, method, options, prior=prior, progress=progress, recorder=recorder)
    return result


def identify_in_run(
    run: BenchRun,
    settings: Settings,
    op: OperatingPoint,
    method: str,
    options: MethodOptions,
    prior: Prior | None = None,
    progress: Callable[[Window], None] | None = None,
    recorder: RunRecorder | None = None,
) -> IdentificationResult:
    """Move the run (service.bench.run.BenchRun) to `op`, settle to the precision the method's target
    needs, run `method` (starting from `prior` where the method uses one). `progress` is called with
    every accepted window (plant time, residual) while the method runs. `recorder`
    (service.store.recordings.RunRecorder) receives the DAQ samples and setpoints from the method's first
    read to its last (the move to the operating point is not part of the identification)."""
    h = run.harmonic_order
    gamma_max = run.commands.gamma_max_rad
    decoupling = run.decoupling
    ident = settings.identification
    closed_loop = ident.s_model == "closed_loop" or (ident.s_model == "auto" and not decoupling)
    with run.operating_point(op, target_db=options.target_db, on_window=progress) as session:
        # the model with the shaft mode as learned on this bench so far (sec. 2.3)
        mode = run.bench.resonance.mode
        s_hat = model_secondary_path(
            settings, op, h, current_loop=closed_loop, resonance_pole=complex(mode.sigma_rad_s, mode.omega_rad_s)
        )
        conditions = Conditions(
            harmonic_frequency_hz=session.harmonic_frequency_hz,
            resonance_hz=mode.frequency_hz,
            current_bandwidth_hz=settings.control.bandwidth_hz,
            decoupling=decoupling,
        )
        session.recorder = recorder
        try:
            result: IdentificationResult = METHODS[method].run(
                session, s_hat, options, gamma_max, prior=prior, conditions=conditions
            )
        except MeasurementError as exc:
            if not exc.over_range:
                raise
            # say why the sensor saturates: a harmonic next to the shaft resonance is amplified by its Q
            distance_hz = abs(conditions.harmonic_frequency_hz - mode.frequency_hz)
            raise MeasurementError(
                f"{exc} (harmonic at {conditions.harmonic_frequency_hz:.0f} Hz, {distance_hz:.0f} Hz "
                f"from the shaft resonance at {mode.frequency_hz:.0f} Hz)",
                over_range=True,
            ) from exc
        finally:
            session.recorder = None
        result.details["op_settle_plant_s"] = session.op_settle_plant_s
        result.details["stale_samples"] = session.stale_samples
        # setpoint toggles that fell into DAQ gaps and were counted once the line was quiet (measurement.py)
        result.details["sync_toggles_hidden"] = session.stream.toggles_hidden
        result.details["speed_rpm_measured"] = session.speed_rpm_measured
        result.details["harmonic_frequency_hz"] = session.harmonic_frequency_hz
        result.details["decoupling"] = decoupling  # the drive must run the LUT with the same setting
        result.details["order_2h"] = result.second_harmonic()  # what cancelling h did to 2h (sec. 2.4)
        result.details["resonance"] = run.bench.resonance.snapshot()
        hold_to_command(result, op, run, settings)
    # wall seconds of the point by what they were spent on (the run's end, make_safe, comes after)
    result.details["bench_time_s"] = run.timing.public()
    return result


def hold_to_command(result: IdentificationResult, op: OperatingPoint, run: BenchRun, settings: Settings) -> None:
    """Record the torque the point ran at (the run's mean torque actual over the measurement) and fail a result
    whose torque left its command beyond the tolerance (service.model.limits.torque_departure): never ok."""
    result.torque_actual_nm, result.details["torque_actual_tpdos"] = run.torque_actual()
    departure = torque_departure(op.torque_nm, result.torque_actual_nm, settings.safety)
    if departure is not None:
        was = f" (the method said {result.status}: {result.message})" if result.message else ""
        result.status, result.message = "failed", departure + was
