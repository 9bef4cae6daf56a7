"""A run-up (issue 27): a speed ramp at constant torque and U_dc, judged as NVH labs do it, by order analysis.

The request (`RunupRequest`, POST /runups) names the torque, U_dc, the speed range [from, to], the ramp rate,
the direction (up: from -> to; down: to -> from; both: up, then down again), what the drive injects
(off; lut: the drive's own LUT in force; theta: one fixed theta in manual mode) and the orders to track
(default: the harmonic order and a survey of orders 1..48).

The run (one bench run: interlocks armed, made safe at the end however it ends): move to the ramp's first
speed and settle there (BenchRun.operating_point), set the injection, ramp (service/bench/speed_ramp.py),
then, once the bench is safe again, computed order tracking over the record (service/model/order_tracking.py,
whose survey of 48 orders over a long ramp takes seconds: never while the bench is held): angle-domain windows of
whole electrical periods, each order's amplitude (sensor full scale) and phase per speed bin of at most
`bin_rpm`, and the noise floor per bin. Both directions' windows are averaged per bin as phasors.

Checks before anything is queued (`check_runup`): the hard limits at the torque, U_dc and both ends of the
range; the envelope model of the motor settings along the whole range (every bin's speed, as a sweep's
grid points are checked), unless overridden; the ramp no longer than `MAX_RAMP_S` per direction (its
samples are held in memory for the analysis: 120 s at 16 kHz is about 50 MB).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, field_validator, model_validator

from service.bench.run import BenchRun
from service.bench.speed_ramp import ramp_through
from service.errors import Invalid
from service.identification.orders import MAX_ORDERS
from service.model.demodulation import ResonanceMode
from service.model.limits import check_limits, check_point
from service.model.operating_point import OperatingPoint
from service.model.order_tracking import DEFAULT_LIST_ABOVE_DB, OrderTrack, prominent_orders, track_orders
from service.names import MAX_NAME_LENGTH, check_name
from service.settings import Settings

MAX_RAMP_S = 120.0  # per direction (module doc)
MAX_ORDER = 48
SURVEY_ORDERS = tuple(range(1, MAX_ORDER + 1))
ENVELOPE_STEP_RPM = 50.0  # the envelope model is checked along the range at this step (and at both ends)


class ThetaSetpoint(BaseModel):
    """A fixed injection of one order for the whole run-up (manual mode), rad."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    order: int | None = Field(
        None, ge=1, le=MAX_ORDER, description="the order this theta is for; null: the bench's harmonic order"
    )
    theta_cos: float = Field(..., ge=-1.0, le=1.0)
    theta_sin: float = Field(..., ge=-1.0, le=1.0)


def injected_thetas(
    theta: ThetaSetpoint | list[ThetaSetpoint], harmonic_order: int
) -> tuple[tuple[float, float], tuple[tuple[int, float, float], ...]]:
    """A run-up's `theta` as the drive takes it (0x2000 and 0x2002): the harmonic order's (0 if not given) and the
    further orders' (order, theta_cos, theta_sin)."""
    main, further = (0.0, 0.0), []
    for t in theta if isinstance(theta, list) else [theta]:
        if t.order is None or t.order == harmonic_order:
            main = (t.theta_cos, t.theta_sin)
        else:
            further.append((t.order, t.theta_cos, t.theta_sin))
    return main, tuple(further)


class RunupRequest(BaseModel):
    """POST /runups (module doc). Every field bounded; the bench's own limits are checked on submit."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    torque_nm: float = Field(..., description="constant torque command along the ramp, Nm")
    udc_v: float = Field(..., gt=0, description="DC-link voltage, V")
    speed_rpm: tuple[float, float] = Field(..., description="[from, to] of the ramp, rpm (from < to)")
    rate_rpm_per_s: float = Field(100.0, gt=0, le=5000.0, description="ramp rate, rpm/s")
    direction: Literal["up", "down", "both"] = Field("up", description="up: from -> to; down: to -> from; both")
    injection: Literal["off", "lut", "theta"] = Field(
        "off", description="off; lut: the LUT in the drive; theta: a fixed theta (field `theta`)"
    )
    theta: ThetaSetpoint | Annotated[list[ThetaSetpoint], Field(min_length=1, max_length=MAX_ORDERS)] | None = Field(
        None,
        description="with injection = theta: the theta applied throughout, {theta_cos, theta_sin} of the harmonic "
        f"order, or per order a list of {{order, theta_cos, theta_sin}} (up to {MAX_ORDERS}, injected summed)",
    )
    orders: list[int] | None = Field(
        None,
        min_length=1,
        max_length=MAX_ORDER,
        description=f"electrical orders to track (1..{MAX_ORDER}); default the harmonic order and orders 1..48",
    )
    bin_rpm: float = Field(10.0, ge=1.0, le=10.0, description="speed bin width of the order analysis, rpm")
    list_above_db: float = Field(
        DEFAULT_LIST_ABOVE_DB,
        ge=0.0,
        le=80.0,
        description="the result's orders_above lists the orders this far above the noise floor over the range, dB",
    )
    override_envelope_model: bool = Field(
        False, description="run where the envelope model of the motor settings refuses (never the hard limits)"
    )
    decoupling: bool | None = Field(
        None,
        description="the drive's decoupling (0x2000:6) along the ramp: a LUT measured with it on holds only with it "
        "on (its theta is another); null: the settings' identification.decoupling",
    )
    # printable text as every name (service/names.py): a NUL or a newline is a 422, not a bench nobody serves
    bench: Annotated[str, AfterValidator(lambda v: check_name(v, "bench name"))] | None = Field(
        None,
        min_length=1,
        max_length=MAX_NAME_LENGTH,
        description="the bench it runs on; default this service's own bench",
    )

    @field_validator("orders")
    @classmethod
    def _orders_in_range(cls, orders: list[int] | None) -> list[int] | None:
        if orders is None:
            return None
        bad = [h for h in orders if not 1 <= h <= MAX_ORDER]
        if bad:
            raise ValueError(f"orders {bad} outside 1..{MAX_ORDER}")
        return sorted(set(orders))

    @model_validator(mode="after")
    def _consistent(self) -> RunupRequest:
        lo, hi = self.speed_rpm
        if not lo < hi:
            raise ValueError(f"speed_rpm [from, to] = [{lo:g}, {hi:g}]: from must be below to")
        if self.injection == "theta" and self.theta is None:
            raise ValueError("injection 'theta' needs the field theta {theta_cos, theta_sin}")
        if self.injection != "theta" and self.theta is not None:
            raise ValueError(f"theta is given but injection is {self.injection!r} (use injection 'theta')")
        if isinstance(self.theta, list):
            named = [t.order for t in self.theta]
            if len(set(named)) != len(named):
                raise ValueError(f"theta names an order twice ({named}; null is the harmonic order)")
        return self

    def ramp_s(self) -> float:
        """Plant seconds of one direction's ramp at the requested rate."""
        return (self.speed_rpm[1] - self.speed_rpm[0]) / self.rate_rpm_per_s

    def orders_tracked(self, harmonic_order: int) -> list[int]:
        return self.orders if self.orders is not None else sorted({harmonic_order, *SURVEY_ORDERS})

    def legs(self) -> list[tuple[float, float]]:
        """The ramps run, in order: (from_rpm, to_rpm) each."""
        lo, hi = self.speed_rpm
        return {"up": [(lo, hi)], "down": [(hi, lo)], "both": [(lo, hi), (hi, lo)]}[self.direction]


def check_runup(req: RunupRequest, settings: Settings) -> None:
    """Refuse (Invalid / LimitError / EnvelopeError naming the field) a run-up this bench may not run (module doc)."""
    if isinstance(req.theta, list):
        # what the request alone cannot tell (it refuses [6, 6]): null is this bench's harmonic order, so on a
        # bench of the 6th [null, 6] names it twice, and one would silently replace the other
        h = settings.identification.harmonic_order
        named = [h if t.order is None else t.order for t in req.theta]
        if len(set(named)) != len(named):
            why = f"theta names an order twice ({named}; null is the harmonic order {h})"
            raise Invalid(why, (("theta", why),))
    lo, hi = req.speed_rpm
    for speed_rpm in (lo, hi):
        check_limits(OperatingPoint(torque_nm=req.torque_nm, speed_rpm=speed_rpm, udc_v=req.udc_v), settings)
    if req.ramp_s() > MAX_RAMP_S:
        why = (
            f"the ramp takes {req.ramp_s():.0f} s per direction at {req.rate_rpm_per_s:g} rpm/s; at most "
            f"{MAX_RAMP_S:g} s: raise rate_rpm_per_s or narrow speed_rpm"
        )
        raise Invalid(why, (("rate_rpm_per_s", why),))
    steps = max(1, math.ceil((hi - lo) / ENVELOPE_STEP_RPM))
    for speed_rpm in np.linspace(lo, hi, steps + 1):
        op = OperatingPoint(torque_nm=req.torque_nm, speed_rpm=float(speed_rpm), udc_v=req.udc_v)
        check_point(op, settings, req.override_envelope_model)


@dataclass(frozen=True)
class RampRecord:
    """What a run-up's ramps read: the DAQ record of every leg (one record: the legs follow each other in the
    stream without a break), and what the run knew of it."""

    angle_rad: np.ndarray
    accel_fs: np.ndarray
    gap_before: np.ndarray
    harmonic_order: int
    settle_plant_s: float
    ramp_plant_s: float
    torque_actual_nm: float | None
    resonance_mode: ResonanceMode


def record_runup(run: BenchRun, settings: Settings, req: RunupRequest, recorder: Any = None) -> RampRecord:
    """The run-up's ramps inside an open run (module doc): move to the first speed, set the injection, ramp."""
    legs = req.legs()
    start = OperatingPoint(torque_nm=req.torque_nm, speed_rpm=legs[0][0], udc_v=req.udc_v)
    with run.operating_point(start) as session:
        if req.injection == "lut":
            session.apply_injection_mode("lut")
        elif req.injection == "theta" and req.theta is not None:
            main, further = injected_thetas(req.theta, session.harmonic_order)
            session.apply_theta(*main, further)
        else:
            session.apply_injection_mode("off")
        session.recorder = recorder
        try:
            samples = ramp_through(session, run.commands, legs, req.rate_rpm_per_s, settings.motor.pole_pairs)
        finally:
            session.recorder = None
        settle_s = session.op_settle_plant_s or 0.0
        torque_actual_nm, _ = run.torque_actual()
    # the ramps' plant time from their samples (a load setpoint is no drive setpoint: the session's clock does not
    # count them), beside the settling at the first speed
    ramp_plant_s = (int(samples.index[-1]) - int(samples.index[0]) + 1) / settings.daq.sample_rate_hz
    return RampRecord(
        samples.angle_rad,
        samples.accel_fs,
        samples.gap_before,
        run.harmonic_order,
        settle_s,
        ramp_plant_s,
        torque_actual_nm,
        run.bench.resonance.mode,
    )


def analyse_runup(record: RampRecord, settings: Settings, req: RunupRequest) -> dict[str, Any]:
    """The order analysis of a run-up's record: its result as stored and answered (each bin averages every leg)."""
    track = track_orders(
        record.angle_rad,
        record.accel_fs,
        settings.daq.sample_rate_hz,
        settings.motor.pole_pairs,
        req.orders_tracked(record.harmonic_order),
        bin_width_rpm=req.bin_rpm,
        gap_before=record.gap_before,
        mode=record.resonance_mode,
    )
    return {
        **track_public(track, req.speed_rpm),
        # the orders to pick for compensation: above the floor over the range, largest first
        "orders_above": [p.public() for p in prominent_orders(track, req.list_above_db)],
        "list_above_db": req.list_above_db,
        "harmonic_order": record.harmonic_order,
        "torque_nm": req.torque_nm,
        "torque_actual_nm": record.torque_actual_nm,
        "udc_v": req.udc_v,
        "direction": req.direction,
        "injection": req.injection,
        "rate_rpm_per_s": req.rate_rpm_per_s,
        "plant_time_s": record.settle_plant_s + record.ramp_plant_s,
        "ramp_plant_s": record.ramp_plant_s,
        "samples": len(record.angle_rad),
    }


def measure_runup(run: BenchRun, settings: Settings, req: RunupRequest, recorder: Any = None) -> dict[str, Any]:
    """Record and analyse a run-up inside an open run (a validation's pairs). The analysis of a survey takes seconds:
    the run goes on reading the DAQ meanwhile (BenchRun.reading_while), so the next point's setpoints are counted
    on a stream without a hole."""
    record = record_runup(run, settings, req, recorder)
    return run.reading_while(lambda: analyse_runup(record, settings, req))


def _finite_or_none(values: np.ndarray) -> list[float | None]:
    return [float(v) if math.isfinite(v) else None for v in values]


def track_public(track: OrderTrack, speed_range_rpm: tuple[float, float]) -> dict[str, Any]:
    """The order analysis as a run-up's result holds it (DESIGN section 6): bins within the requested range (the
    shaft holding its end speeds may add a bin just beyond either end), NaN (an order not fitted, an empty bin)
    as null."""
    lo, hi = speed_range_rpm
    keep = (track.speed_rpm >= lo - track.bin_width_rpm) & (track.speed_rpm <= hi + track.bin_width_rpm)
    return {
        "speed_rpm": [float(v) for v in track.speed_rpm[keep]],
        "orders": list(track.orders),
        "amplitude": [_finite_or_none(row[keep]) for row in track.amplitude_fs],
        "phase_deg": [_finite_or_none(row[keep]) for row in track.phase_deg],
        "noise_floor": _finite_or_none(track.noise_floor_fs[keep]),
        "windows": [int(v) for v in track.windows[keep]],
        "bin_rpm": track.bin_width_rpm,
    }


def runup_in_run(
    bench: Any, settings: Settings, req: RunupRequest, cancel: threading.Event | None, recorder: Any = None
) -> dict[str, Any]:
    """A run-up as a run of its own: the bench held, the interlocks armed, made safe at the end; the order analysis
    after it (the survey of 48 orders over a long ramp takes seconds: the bench is not held, nor its watchdog
    starved, meanwhile)."""
    decoupling = settings.identification.decoupling if req.decoupling is None else req.decoupling
    with bench.run(settings.identification.harmonic_order, decoupling=decoupling, cancel=cancel) as run:
        record = record_runup(run, settings, req, recorder)
    return analyse_runup(record, settings, req)
