"""Pieces every method shares: the uncompensated reference, window precision, the target and the
verdict (status and a reason a test engineer can act on), the prior a sweep hands to a point, and
the trace snippets.

Target and noise (all amplitudes in sensor full scale, fs): the target amplitude is
A_target = |A_0| 10^(-target_db/20) with A_0 the uncompensated phasor. A window's phasor carries
white-ish noise of standard deviation sigma per component (service.model.demodulation); a residual counts
as meeting the target only when |a| + 2 sigma <= A_target, so a lucky noise draw never makes a
result `ok`. The noise floor of a result is the rms amplitude of a noise phasor, sqrt(2) sigma of
its final window, in dB against |A_0|.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from service.identification.session import MeasurementError, MeasurementSession, Window
from service.model.harmonic import amplitude_spectrum

SPECTRUM_MAX_ORDER = 24
SNIPPET_SAMPLES = 800
CONFIDENCE_SIGMAS = 2.0  # |a| + 2 sigma <= A_target counts as met
AT_FLOOR_SIGMAS = 3.0  # |A| <= 3 sqrt(2) sigma: the residual is not resolved from the window's noise
PRECISION_FOR_TARGET = 5.0  # a window meant to confirm the target has sigma <= A_target / 5
MIN_PERIODS = 12  # two electrical turns at h = 6: every integer order but h averages out


def floor_amplitude(noise_std_fs: Any) -> Any:
    """The amplitude at and below which a phasor is not resolved from a window's noise (AT_FLOOR_SIGMAS), fs;
    element-wise over an array of noises (several orders measured in one window, orders.py)."""
    return AT_FLOOR_SIGMAS * math.sqrt(2.0) * noise_std_fs


class MethodOptions(BaseModel):
    """Options every method has: the target, the injection limit, the window bounds. Finite numbers
    only, every field bounded (no request can ask for unbounded plant time or memory)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    target_db: float = Field(40.0, ge=0, le=80, description="suppression the result must reach to be ok, dB")
    gamma_max_deg: float | None = Field(None, gt=0, le=45, description="defaults to the settings' gamma_max")
    max_window_s: float = Field(0.4, gt=0, le=5.0, description="longest window a precision need may extend to, plant s")
    settle_s: float = Field(
        0.005,
        ge=0,
        le=2.0,
        description="plant time after each theta before measuring "
        "(the shaft mode a step excites is fitted, not waited out)",
    )
    stop_margin_db: float | None = Field(
        None,
        ge=0,
        le=20,
        description="keep improving until the residual is this "
        "far below the target (ok is still judged at target_db): a cell meant for a "
        "LUT must hold its target in a later session and in the drive's LUT mode. "
        "Default: 0 for one identification, LUT_MARGIN_DB (6) for sweep and "
        "refinement cells",
    )
    decoupling: bool | None = Field(
        None,
        description="drive decoupling of nominal control and injection (0x2000:6, "
        "sec. 3.1) for this run; at low speed the nominal current loop counteracts the "
        "injection without it (sec. 2.4). Default: the settings' identification.decoupling. "
        "A map is valid in the drive only with the decoupling it was measured with",
    )
    override_envelope_model: bool = Field(
        False,
        description="run points the envelope model of the motor settings refuses (service.model.limits."
        "check_envelope), for a machine known to exceed its nominal settings; never the hard limits "
        "(max torque, max speed, torque sign), which the actuals interlock holds on what the motor does",
    )


@dataclass(frozen=True)
class Prior:
    """What a point starts from: theta (rad) and, if measured, the 2x2 S_ss (fs/rad), e.g. from the
    neighbouring cells of a sweep (docs/conventions.md, Beyond the paper (c))."""

    theta_cos: float
    theta_sin: float
    s_matrix: tuple[tuple[float, float], tuple[float, float]] | None = None
    source: str = ""
    # several orders (method probe-orders): the neighbour's theta of its further orders ((order, cos, sin), rad),
    # and the whole J it measured (2K x 2K, fs/rad) over `jacobian_orders`, the stacked orders' [cos, sin]
    further: tuple[tuple[int, float, float], ...] = ()
    jacobian: tuple[tuple[float, ...], ...] | None = None
    jacobian_orders: tuple[int, ...] = ()

    @property
    def theta(self) -> np.ndarray:
        return np.array([self.theta_cos, self.theta_sin])

    def orders_theta(self, orders: list[int]) -> np.ndarray:
        """theta stacked over `orders` (the first is this prior's own), 0 for an order it has none of."""
        own = {h: (c, s) for h, c, s in self.further}
        rest = [v for h in orders[1:] for v in own.get(h, (0.0, 0.0))]
        return np.array([self.theta_cos, self.theta_sin, *rest])

    def orders_jacobian(self, orders: list[int]) -> np.ndarray | None:
        """The neighbour's J where it was measured over exactly `orders` (in that order), else None."""
        if self.jacobian is None or list(self.jacobian_orders) != list(orders):
            return None
        j = np.array(self.jacobian, dtype=float)
        return j if j.shape == (2 * len(orders), 2 * len(orders)) and abs(np.linalg.det(j)) > 1e-300 else None

    def s(self) -> np.ndarray | None:
        return None if self.s_matrix is None else np.array(self.s_matrix, dtype=float)


LUT_MARGIN_DB = 6.0  # sweep cells: their LUT entry holds 40 dB in a later session (measured: issue 17 note)


def target_amplitude(uncompensated_fs: float, target_db: float) -> float:
    gain: float = 10.0 ** (-target_db / 20.0)  # a float's power of a float: typed Any
    return uncompensated_fs * gain


def stop_amplitude(uncompensated_fs: float, options: "MethodOptions") -> float:
    """Where a method stops improving: the target plus its margin (options.stop_margin_db; ok is still
    judged at target_db alone, common.verdict)."""
    return target_amplitude(uncompensated_fs, options.target_db + (options.stop_margin_db or 0.0))


def done(window: Window, target_fs: float, stop_fs: float) -> bool:
    """A method may stop: the target met with confidence (meets) and the residual itself down to the
    margin. The margin asks for a further step, never for longer windows: the windows stay sized for
    the target's precision (PRECISION_FOR_TARGET), which is what the verdict needs."""
    return meets(window, target_fs) and window.phasor.amplitude <= stop_fs


def meets(window: Window, amplitude_limit_fs: float) -> bool:
    """The residual is below the limit with confidence (module doc)."""
    return not bool(short_of(window.phasor.amplitude, window.noise_std_fs, amplitude_limit_fs))


def short_of(amplitude_fs: Any, noise_std_fs: Any, amplitude_limit_fs: Any) -> Any:
    """Not below the limit with confidence: |a| + CONFIDENCE_SIGMAS sigma > limit; element-wise over arrays of
    amplitudes and limits (several orders measured in one window, orders.py)."""
    return amplitude_fs + CONFIDENCE_SIGMAS * noise_std_fs > amplitude_limit_fs


def periods_for(session: MeasurementSession, seconds: float) -> int:
    """Whole electrical turns (multiples of h periods) spanning at least `seconds` of plant time, >= MIN_PERIODS."""
    h = session.harmonic_order
    periods = math.ceil(seconds * session.harmonic_frequency_hz / h) * h
    return max(MIN_PERIODS, periods)


def measure_reference(
    session: MeasurementSession, min_periods: int, max_periods: int, relative_precision: float = 0.01
) -> Window:
    """The uncompensated reference (theta = 0), its phasor known to `relative_precision` of itself
    (1 % = +-0.1 dB on every suppression figure) unless that needs more than `max_periods`."""
    session.apply_theta(0.0, 0.0)
    first = session.measure(min_periods)
    if first.noise_std_fs <= relative_precision * first.phasor.amplitude:
        return first
    return session.measure(
        min_periods, max_noise_std_fs=relative_precision * first.phasor.amplitude, max_periods=max_periods
    )


def measure_step(
    session: MeasurementSession, periods: int, max_periods: int, target_fs: float, expected_fs: float
) -> Window | None:
    """The window after a step: resolve what the step is expected to leave to 1/20, never coarser than
    the target needs (1/PRECISION_FOR_TARGET of it). None where the step drove the sensor over range:
    a failed step, the caller steps back."""
    try:
        return session.measure(
            periods, max_noise_std_fs=max(target_fs / PRECISION_FOR_TARGET, expected_fs / 20), max_periods=max_periods
        )
    except MeasurementError as exc:
        if not exc.over_range:
            raise
        return None


def noise_floor_db(window: Window, uncompensated_fs: float) -> float | None:
    if window.noise_std_fs <= 0 or uncompensated_fs <= 0:
        return None
    return 20.0 * math.log10(math.sqrt(2.0) * window.noise_std_fs / uncompensated_fs)


@dataclass(frozen=True)
class Conditions:
    """What the verdict needs to know about the operating point (all from the service's own knowledge)."""

    harmonic_frequency_hz: float
    resonance_hz: float | None = None
    current_bandwidth_hz: float | None = None
    decoupling: bool = False


RESONANCE_NEAR_HZ = 150.0  # closer than this, the shaft mode dominates every window after a step
CURRENT_LOOP_NEAR = 2.0  # f_h below this times the current-loop bandwidth: the loop counteracts (sec. 2.4)


def verdict(
    suppression_db: float,
    target_db: float,
    final: Window,
    uncompensated_fs: float,
    conditions: Conditions | None,
    limited: bool,
) -> tuple[str, str]:
    """(status, reason). `ok` only when the final window met the target with confidence."""
    limit = target_amplitude(uncompensated_fs, target_db)
    if meets(final, limit):
        return "ok", f"{suppression_db:.1f} dB, target {target_db:g} dB met"
    counteracts = None
    if (
        conditions is not None
        and conditions.current_bandwidth_hz
        and not conditions.decoupling
        and conditions.harmonic_frequency_hz < CURRENT_LOOP_NEAR * conditions.current_bandwidth_hz
    ):
        counteracts = (
            f"the nominal current loop ({conditions.current_bandwidth_hz:.0f} Hz) counteracts at "
            f"{conditions.harmonic_frequency_hz:.0f} Hz: enable decoupling (option decoupling = true)"
        )
    if limited:
        return "no_authority", (
            f"gamma_max reached at {suppression_db:.1f} dB: the injection cannot cancel the "
            "harmonic here (sec. 2.4)" + (f"; {counteracts}" if counteracts else "")
        )
    reasons = []
    floor = noise_floor_db(final, uncompensated_fs)
    if floor is not None and final.phasor.amplitude <= floor_amplitude(final.noise_std_fs):
        reasons.append(f"residual at the sensor noise floor, {floor:.0f} dB")
    if conditions is not None:
        if conditions.resonance_hz is not None:
            distance = abs(conditions.harmonic_frequency_hz - conditions.resonance_hz)
            if distance < RESONANCE_NEAR_HZ:
                reasons.append(
                    f"harmonic {distance:.0f} Hz from the shaft resonance ({conditions.resonance_hz:.0f} Hz)"
                )
        if counteracts:
            reasons.append(counteracts)
    if not reasons:
        reasons.append("the residual stopped falling")
    if suppression_db >= target_db:
        # the figure is at target but a noise draw could have made it so: say what is confirmed
        bound = final.phasor.amplitude + CONFIDENCE_SIGMAS * final.noise_std_fs
        confirmed_db = 20.0 * math.log10(uncompensated_fs / bound) if bound > 0 and uncompensated_fs > 0 else math.nan
        head = (
            f"{suppression_db:.1f} dB, not confirmed at the {target_db:g} dB target (with {CONFIDENCE_SIGMAS:g} "
            f"sigma of the window's noise, {confirmed_db:.1f} dB)"
        )
    else:
        head = f"{suppression_db:.1f} dB, below the {target_db:g} dB target"
    return "below_target", f"{head}: " + "; ".join(reasons)


def spectrum_traces(before: Window | None, after: Window) -> dict[str, Any]:
    """Data for the paper's Fig. 10: alpha over a few periods and its order spectrum, before/after."""

    def snippet(w: Window) -> dict[str, Any]:
        n = min(SNIPPET_SAMPLES, len(w.alpha_fs))
        return {
            "angle_rad": np.round(np.unwrap(w.angle_rad[:n]), 5).tolist(),
            "alpha_fs": np.round(w.alpha_fs[:n], 6).tolist(),
        }

    traces = {
        "spectrum_after": amplitude_spectrum(after.alpha_fs, after.angle_rad, SPECTRUM_MAX_ORDER),
        "alpha_after": snippet(after),
    }
    if before is not None:
        traces.update(
            {
                "spectrum_before": amplitude_spectrum(before.alpha_fs, before.angle_rad, SPECTRUM_MAX_ORDER),
                "alpha_before": snippet(before),
            }
        )
    return traces


def time_to_suppression(history: list[list[float]], uncompensated_amplitude: float, target_db: float) -> float | None:
    """Plant time (s) at the end of the first window whose residual is `target_db` below the
    uncompensated amplitude; None if none was. history rows: [plant_time_s, theta_cos, theta_sin, amplitude]."""
    limit = uncompensated_amplitude * 10 ** (-target_db / 20.0)
    for t, _tc, _ts, amp in history[1:]:
        if amp <= limit:
            return t
    return None


def clamp(theta: np.ndarray, gamma_max_rad: float) -> tuple[np.ndarray, bool]:
    """theta scaled back onto |theta| = gamma_max (anti-windup of sec. 2.4); (theta, limited)."""
    gamma = float(np.hypot(*theta))
    if gamma > gamma_max_rad:
        return theta * (gamma_max_rad / gamma), True
    return theta, False


def affine_s_from_history(thetas: np.ndarray, phasors: np.ndarray, min_spread_rad: float) -> np.ndarray | None:
    """S_ss (2x2) of the affine model a = S_ss theta + b fitted over a run's own windows (least
    squares, docs/conventions.md, Beyond the paper (c)); None while the thetas do not span both
    directions by `min_spread_rad`."""
    if len(thetas) < 3:
        return None
    centred = thetas - thetas.mean(axis=0)
    singular = np.linalg.svd(centred, compute_uv=False)
    if singular[-1] / math.sqrt(len(thetas)) < min_spread_rad:
        return None
    design = np.column_stack([thetas, np.ones(len(thetas))])
    coef, *_ = np.linalg.lstsq(design, phasors, rcond=None)
    s_ss: np.ndarray = coef[:2].T
    return s_ss
