"""Several orders at one operating point, jointly (issue 28): the probe method (probe.py) on the stacked theta of
every order, its Jacobian measured by probes with the cross-paths between orders in it.

theta = [theta_cos, theta_sin] per order, stacked (rad); a = [a_c, a_s] per order, stacked (fs), every
order's phasor from the same window (windows span whole electrical turns: every integer order is whole in
them). The drive injects the orders' angles summed and rotates the voltage once by the sum (eq. 2-4, 0x2002),
so near theta the plant is a(theta + d) = a(theta) + J d with J (2K x 2K, real): the diagonal blocks are each
order's S_ss (eq. 15), the off-diagonal blocks the cross-paths. They are not zero: the rotation's gamma^2 term
makes order 2h depend on Theta_h^2 (sec. 2.4, eq. 5-6), and the product of order h's and order 2h's angles
feeds back into order h. So J is measured whole: a probe of one order's component moves every order's phasor,
and that column of J is all of it.

Steps: the reference at theta = 0 (every order's uncompensated phasor); 2K probes around it (J, column by
column); Newton steps theta <- theta - J^-1 a on all orders at once, each step refining J by Broyden's update
(as probe.py; the cross-path grows with theta_h, so the secant through the steps is what holds near theta*);
the sum of the orders' |theta| kept at most gamma_max (the drive's own limit, 0x2000:5). A step's window resolves
each order to a third of its target (up to the longest window, confirm_window_s). It stops when every order meets
its target with confidence and its margin, when a step no longer improves the worst order, or after
max_newton_steps; the best theta is confirmed with the precision the smallest target needs (and stepped once more
from that window if it resolved an order short of its target). An order whose target lies within 3 sigma of the
longest window's noise (judged from the reference, sigma ~ 1/sqrt(samples)) is said not confirmable here: no
window is sized for it, and it is stepped only while a window resolves it.

Every order is judged on its own (common.verdict with its own uncompensated phasor, target and noise: the window's
residual density about that order's frequency, the other orders fitted beside it, session.order_window; the noise
about the 6th is not the noise about the 12th near the drive's voltage limit, measured): the result's
own fields are the first order's (the run's harmonic order), `details.orders` lists every order
{order, status, theta_cos, theta_sin, gamma_deg, delta_deg, suppression_db, target_db, reason}, and
`details.jacobian` the measured J (`cross_paths`: its off-diagonal blocks, fs/rad).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
from pydantic import Field, field_validator

from drivers.injection_limit import injection_scale
from service.identification.common import (
    CONFIDENCE_SIGMAS,
    PRECISION_FOR_TARGET,
    Conditions,
    Prior,
    floor_amplitude,
    noise_floor_db,
    periods_for,
    short_of,
    spectrum_traces,
    stop_amplitude,
    target_amplitude,
    verdict,
)
from service.identification.probe import ProbeOptions
from service.identification.result import IdentificationResult
from service.identification.session import MeasurementError, MeasurementSession, Window
from service.model.harmonic import Phasor
from service.model.secondary_path import gamma_delta

MAX_ORDERS = 4  # the drive injects the run's order and up to 3 further ones (0x2002)
MAX_ORDER = 48
# a step's window resolves each order to a third of its target: the step from it lands near 0.3-0.5 of the target
# and the next window confirms (an ideal pair of windows has sigma ~ 0.3 L each: bench_two_order_map's floor);
# a fifth (PRECISION_FOR_TARGET, the confirmation's) in every step cost more windows than it saved (measured, the
# 10 x 10 map on four machines: the same orders ok, 16 % more plant time)
STEP_PRECISION = 3.0
# an order's target is confirmable when the residual may sit a sigma below it and still be confirmed with
# CONFIDENCE_SIGMAS (common.meets) in the longest window: limit >= (CONFIDENCE_SIGMAS + 1) sigma
CONFIRMABLE_SIGMAS = CONFIDENCE_SIGMAS + 1.0
NOT_CONFIRMABLE = "not confirmable here"  # the reason's words for such an order (bench_two_order_map counts them)


class OrdersOptions(ProbeOptions):
    orders: list[int] = Field(
        [6, 12],
        min_length=1,
        max_length=MAX_ORDERS,
        description=f"electrical orders cancelled jointly (1..{MAX_ORDER}, at most {MAX_ORDERS}); the run's harmonic "
        "order among them",
    )

    # the orders converge together: a step for one moves the others (the cross-paths), so more steps than one order's
    max_newton_steps: int = Field(10, ge=1, le=50)
    confirm_window_s: float = Field(
        1.2,
        gt=0,
        le=5.0,
        description="longest window of the confirmation where the steps ended with an order unresolved from its noise "
        "(a smaller order, the 12th, near the sensor's noise needs a longer window than a step's), plant s",
    )

    @field_validator("orders")
    @classmethod
    def _distinct_in_range(cls, orders: list[int]) -> list[int]:
        bad = [h for h in orders if not 1 <= h <= MAX_ORDER]
        if bad:
            raise ValueError(f"orders {bad} outside 1..{MAX_ORDER}")
        return distinct_orders(orders)

    def plant_time_bound_s(self, harmonic_frequency_hz: float) -> float:
        """Worst case: the reference (twice), the prior's start, 2 probes per order (twice: a neighbour's J that does
        not hold) at max_window_s; the Newton steps, the confirmation and the step after it at confirm_window_s."""
        short = 4 * len(self.orders) + 3
        long = self.max_newton_steps + 2
        return short * (self.max_window_s + self.settle_s) + long * (
            max(self.confirm_window_s, self.max_window_s) + self.settle_s
        )


def noise_at(window: Window, session: MeasurementSession, periods: int, noise_std_fs: Any = None) -> Any:
    """The noise std of each phasor component a window of `periods` would have, from `window`'s (fs; or from
    `noise_std_fs`, every order's over that window): white within each order's band, so sigma ~ 1/sqrt(samples)."""
    samples = periods / session.harmonic_frequency_hz * session.sample_rate_hz
    noise = window.noise_std_fs if noise_std_fs is None else noise_std_fs
    return noise * math.sqrt(window.phasor.samples / max(samples, 1.0))


def distinct_orders(orders: list[int]) -> list[int]:
    """`orders` as given; ValueError if one is named twice (the options' and a request's `orders` alike)."""
    if len(set(orders)) != len(orders):
        raise ValueError(f"orders {orders} name an order twice")
    return orders


def order_phasors(session: MeasurementSession, window: Window, orders: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """[a_c, a_s] of every order, stacked, and every order's noise std per phasor component (fs): the session's own
    order from the window's fit, the others by the session over the same window (session.order_window: with the
    shaft mode as a nuisance, as its own, and the noise about its own frequency, which is what acts on its phasor)."""
    out, noise = [], []
    for h in orders:
        w = window if h == session.harmonic_order else session.order_window(window, h, tuple(orders))
        out += [w.phasor.a_c, w.phasor.a_s]
        noise.append(w.noise_std_fs)
    return np.array(out), np.array(noise)


def _per_order(a: np.ndarray) -> np.ndarray:
    """|a| of every order from the stacked [a_c, a_s, ...]."""
    return np.asarray(np.hypot(a[0::2], a[1::2]), dtype=float)


def _further(orders: list[int], theta: np.ndarray) -> tuple[tuple[int, float, float], ...]:
    return tuple((h, float(theta[2 * k]), float(theta[2 * k + 1])) for k, h in enumerate(orders) if k)


def _clamp_sum(theta: np.ndarray, gamma_max_rad: float) -> tuple[np.ndarray, bool]:
    """Every order's theta scaled by one factor so that the sum of their |theta| is at most gamma_max (what the
    drive does, 0x2000:5); (theta, limited)."""
    k = injection_scale(_per_order(theta).tolist(), gamma_max_rad)
    return (theta * k, True) if k < 1.0 else (theta, False)


def identify_orders(
    session: MeasurementSession,
    s_hat: complex,
    options: OrdersOptions,
    gamma_max_rad: float,
    *,
    prior: Prior | None = None,
    conditions: Conditions | None = None,
    **_unused: Any,
) -> IdentificationResult:
    """Probe + Newton on every order of options.orders at once (module doc)."""
    h = session.harmonic_order
    if h not in options.orders:
        raise MeasurementError(f"orders {options.orders} do not include the run's harmonic order {h}")
    orders = [h] + [o for o in options.orders if o != h]
    n = len(orders)
    session.settle_after_theta_s = options.settle_s
    session.also_orders = tuple(orders[1:])  # the run's own order fitted with the others beside, as they are
    min_periods = periods_for(session, options.window_s)
    max_periods = max(min_periods, periods_for(session, options.max_window_s))
    history: list[list[float]] = []

    # each order's noise against the run's own order's over one window (their bands differ: near the voltage limit
    # the drive's lines about the 6th are not those about the 12th), from the last window: what a noise limit on
    # every order asks of the window, whose extension session.measure judges on its own order
    noise_ratio = np.ones(n)

    def measure(
        theta: np.ndarray, noise_limit_fs: np.ndarray | None, longest: int = max_periods
    ) -> tuple[Window, np.ndarray, np.ndarray]:
        """The window at theta, every order's phasor and noise; `noise_limit_fs`: per order (inf: none)."""
        nonlocal noise_ratio
        session.apply_theta(float(theta[0]), float(theta[1]), _further(orders, theta))
        limit = None if noise_limit_fs is None else float(np.min(noise_limit_fs / noise_ratio))
        w = session.measure(min_periods, max_noise_std_fs=None if limit == math.inf else limit, max_periods=longest)
        a, noise = order_phasors(session, w, orders)
        if noise[0] > 0 and np.all(noise > 0):
            noise_ratio = noise / noise[0]
        history.append([w.end_time_s, *theta.tolist(), *_per_order(a).tolist()])
        return w, a, noise

    def only(mask: np.ndarray, values: np.ndarray) -> np.ndarray:
        """`values` where `mask`, no limit elsewhere."""
        return np.where(mask, values, math.inf)

    # an order whose target lies within the noise of the longest window cannot be confirmed at any window this
    # run may take: it is still cancelled while a window resolves it, but no window is sized for its target
    longest_periods = max(max_periods, periods_for(session, options.confirm_window_s))

    def limits_of(amplitudes: np.ndarray) -> np.ndarray:
        return np.array([target_amplitude(u, options.target_db) for u in amplitudes])

    def confirmable_in(window: Window, noise: np.ndarray, limits: np.ndarray) -> np.ndarray:
        return np.asarray(limits >= CONFIRMABLE_SIGMAS * noise_at(window, session, longest_periods, noise))

    theta = np.zeros(2 * n)
    # the reference: every confirmable order's phasor to 1 % of itself (+-0.1 dB on each suppression figure)
    before, a0, noise0 = measure(theta, None)
    first = _per_order(a0)
    confirmable = confirmable_in(before, noise0, limits_of(first))
    if np.any(noise0[confirmable] > 0.01 * first[confirmable]):
        before, a0, noise0 = measure(theta, only(confirmable, 0.01 * first))
    uncompensated = _per_order(a0)
    if np.any(uncompensated <= 0):
        raise MeasurementError("an order reads exactly zero without compensation: nothing to cancel")
    limits = limits_of(uncompensated)
    stops = np.array([stop_amplitude(u, options) for u in uncompensated])
    confirmable = confirmable_in(before, noise0, limits)
    longest_noise_fs = noise_at(before, session, longest_periods, noise0)
    # the orders a window is sized to resolve (an order not confirmable here sizes none, unless none is confirmable)
    sized = confirmable if np.any(confirmable) else np.ones(n, dtype=bool)

    # the probes: each order's from the model's |theta*| of the main order, scaled by that order's amplitude
    model_theta_rad = uncompensated[0] / abs(s_hat)
    probe_rad = np.array(
        [
            min(
                max(
                    options.probe_fraction * model_theta_rad * u / uncompensated[0], math.radians(options.probe_min_deg)
                ),
                math.radians(options.probe_max_deg),
                gamma_max_rad / (2 * n),
            )
            for u in uncompensated
        ]
    )

    def probe_jacobian() -> np.ndarray:
        """J column by column: each component of each order probed around theta = 0 (a0)."""
        columns = []
        for k in range(2 * n):
            step = np.zeros(2 * n)
            step[k] = probe_rad[k // 2]
            # the probe's response (about probe_fraction of every order's amplitude) resolved to a fiftieth
            _probe_window, a_k, _noise = measure(step, only(sized, options.probe_fraction * uncompensated / 50.0))
            columns.append((a_k - a0) / step[k])
        probed_j = np.column_stack(columns)
        if abs(np.linalg.det(probed_j)) < 1e-300:
            raise MeasurementError(
                "the probes do not move every order: the injection has no effect on one of them here"
            )
        return probed_j

    # a, the phasors stepped from, and the noise std of the window that measured them (fs): whether a step may
    # use an order's phasor is judged by its own window's noise, not by the last window's (a probe's, a step's)
    a, a_noise_fs = a0, noise0
    use = prior if options.use_prior else None
    start = None if use is None else use.orders_theta(orders)
    prior_j = None if use is None else use.orders_jacobian(orders)
    notes: list[str] = []
    if start is not None and np.any(start):
        # the neighbours' theta of every order: the first step starts some 20 dB down (as probe.py)
        start, _ = _clamp_sum(start, gamma_max_rad)
        _start_w, a_start, start_noise = measure(start, only(sized, uncompensated / 50.0))
        if float(np.max(_per_order(a_start) / uncompensated)) < 1.0:
            theta, a, a_noise_fs = start, a_start, start_noise
            notes.append(f"started from {use.source if use is not None else 'a prior'}")
    if prior_j is not None:
        jacobian, probed = prior_j, None  # the neighbour's J (same speed): probed again only if it does not hold
        notes.append("J from the neighbour at the same speed")
    else:
        jacobian = probe_jacobian()
        probed = jacobian.copy()

    # each order against what can be confirmed of it here: its target, or for an order not confirmable here the
    # least amplitude the longest window confirms (else its tiny target would make it the worst at every point)
    scales = np.maximum(limits, CONFIRMABLE_SIGMAS * longest_noise_fs)

    def worst(a: np.ndarray) -> float:
        return float(np.max(_per_order(a) / scales))

    best_theta, best_a, best_noise_fs = theta.copy(), a, a_noise_fs  # the point whose worst order is least
    limited = False
    failures, damping, steps = 0, 1.0, 0
    final: tuple[Window, np.ndarray, np.ndarray] | None = None
    for steps in range(1, options.max_newton_steps + 1):
        # an order not confirmable here steps only while the window that measured it resolved it from its noise: a
        # step on its noise would inject a 12th of the noise's size, larger than the order itself
        resolved_now = _per_order(a) > floor_amplitude(a_noise_fs)
        free = np.repeat(confirmable | resolved_now, 2)
        if not np.any(free):
            break
        d_theta = np.zeros(2 * n)
        d_theta[free] = np.linalg.solve(jacobian[np.ix_(free, free)], a[free])
        target, limited = _clamp_sum(theta - damping * d_theta, gamma_max_rad)
        try:
            # every order resolved to what it needs: a twentieth of what it has now (a step is expected to leave
            # a tenth), never finer than its target needs; one window, so the most demanding order decides
            # (an order not confirmable here: a fifth of what it has, while a window resolves it)
            need = np.where(confirmable, np.maximum(limits / STEP_PRECISION, _per_order(a) / 20.0), _per_order(a) / 5.0)
            # up to the longest window: an order the step windows of max_window_s no longer resolve to a third of its
            # target would only walk on their noise, each step a window lost
            w, new_a, new_noise = measure(target, only(free[0::2], need), longest_periods)
        except MeasurementError as exc:
            if not exc.over_range:
                raise
            failures, damping = failures + 1, 0.5 * damping
            continue
        d_theta, d_a = target - theta, new_a - a
        # a step too small to move the phasors above their noise would teach J the noise (as probe.py)
        if float(np.linalg.norm(jacobian @ d_theta)) > 20.0 * max(float(np.sqrt(2.0 * np.sum(new_noise**2))), 1e-12):
            broyden = jacobian + np.outer(d_a - jacobian @ d_theta, d_theta) / float(d_theta @ d_theta)
            if abs(np.linalg.det(broyden)) > 1e-300:
                jacobian = broyden
        amplitudes = _per_order(new_a)
        # every order done as common.done judges one: its target met with confidence and its margin reached
        open_orders = short_of(amplitudes, new_noise, limits) | (amplitudes > stops)
        # an order not confirmable here stays open while this window resolves it (the others' injection raises
        # it: the rotation's gamma^2 term puts order h's angle squared on order 2h, sec. 2.4)
        open_orders &= confirmable | (amplitudes > floor_amplitude(new_noise))
        if not np.any(open_orders):
            final, best_theta = (w, new_a, new_noise), target.copy()
            break
        # an open order whose residual the longest window allowed no longer resolves from its noise has nothing
        # left to steer by (a shorter window's noise says only that the window was short)
        floor_fs = floor_amplitude(new_noise) if w.phasor.periods >= longest_periods else np.zeros(n)
        resolved = open_orders & (amplitudes > floor_fs)
        # progress: any open order still resolved down by a fifth from the point stepped from, the worst order no
        # worse (the orders converge at their own pace: the smallest one near its noise must not stop the others,
        # nor keep them stepping; not each order's lowest so far: the 6th's injection raises the 12th on the way)
        improved = bool(np.any((amplitudes < 0.8 * _per_order(a)) & resolved)) and worst(new_a) < worst(a)
        if worst(new_a) < worst(best_a):
            best_theta, best_a, best_noise_fs = target.copy(), new_a, new_noise
        if not np.any(resolved):
            break  # every open order at its noise floor: only a longer window (the confirmation's) tells more
        failures = 0 if improved else failures + 1
        damping = 1.0 if improved else 0.5 * damping
        if failures >= 2 and probed is None:
            # the neighbour's J does not hold here: measured by the probes, Newton from the best point so far
            jacobian = probe_jacobian()
            probed = jacobian.copy()
            notes.append("the neighbour's J did not hold here: measured by probes")
            failures, damping = 0, 1.0
            theta, a, a_noise_fs = best_theta.copy(), best_a, best_noise_fs
            continue
        if failures >= 2:
            break  # no order improves any more: noise floor or non-linearity
        theta, a, a_noise_fs = (target, new_a, new_noise) if improved else (best_theta.copy(), best_a, best_noise_fs)
    if final is None:
        # the confirmation: as long as the smallest confirmable target needs, up to confirm_window_s
        if np.any(confirmable):
            confirm_fs = only(confirmable, limits / PRECISION_FOR_TARGET)
            final = measure(best_theta, confirm_fs, longest_periods)
            # the confirmation resolved an order the steps' windows could not and found it short of its target:
            # one more joint step from this precise window, confirmed by a window as long (kept if no order lost)
            w, a, noise = final
            amplitudes = _per_order(a)
            short = confirmable & short_of(amplitudes, noise, limits)
            if np.any(short & (amplitudes > floor_amplitude(noise))):
                stepped, stepped_limited = _clamp_sum(best_theta - np.linalg.solve(jacobian, a), gamma_max_rad)
                again = measure(stepped, confirm_fs, longest_periods)
                if worst(again[1]) < worst(a):
                    final, best_theta, limited = again, stepped, stepped_limited
                    notes.append("one more step after the confirmation")
        else:
            final = measure(best_theta, None, max_periods)
    final_w, final_a, final_noise = final

    per_order = []
    for k, order in enumerate(orders):
        residual = Phasor(
            float(final_a[2 * k]), float(final_a[2 * k + 1]), final_w.phasor.samples, final_w.phasor.periods
        )
        suppression = 20.0 * math.log10(uncompensated[k] / max(residual.amplitude, 1e-300))
        order_final = replace(final_w, phasor=residual, noise_std_fs=float(final_noise[k]))
        status, reason = verdict(
            suppression,
            options.target_db,
            order_final,
            float(uncompensated[k]),
            conditions if k == 0 else None,
            limited,
        )
        if status != "ok" and not confirmable[k]:
            standing_db = 20.0 * math.log10(uncompensated[k] / (CONFIRMABLE_SIGMAS * longest_noise_fs[k]))
            reason += (
                f"; {NOT_CONFIRMABLE}: the order stands {standing_db:.1f} dB above {CONFIRMABLE_SIGMAS:g} sigma of "
                f"the longest window's noise ({options.confirm_window_s:g} s), {options.target_db:g} dB asked"
            )
        gamma_rad, delta_rad = gamma_delta(float(best_theta[2 * k]), float(best_theta[2 * k + 1]))
        per_order.append(
            {
                "order": order,
                "status": status,
                "theta_cos": float(best_theta[2 * k]),
                "theta_sin": float(best_theta[2 * k + 1]),
                "gamma_deg": math.degrees(gamma_rad),
                "delta_deg": math.degrees(delta_rad),
                "suppression_db": suppression,
                "target_db": options.target_db,
                # the final window's noise against this order's uncompensated amplitude: how far 40 dB is resolvable
                "noise_floor_db": noise_floor_db(order_final, float(uncompensated[k])),
                "reason": reason,
                "uncompensated": {
                    "a_c": float(a0[2 * k]),
                    "a_s": float(a0[2 * k + 1]),
                    "amplitude": float(uncompensated[k]),
                },
                "residual": residual.as_dict(),
            }
        )
    first_order = per_order[0]
    others = "; ".join(f"order {o['order']}: {o['status']}, {o['suppression_db']:.1f} dB" for o in per_order[1:])
    started = "".join(f"; {note}" for note in notes)
    message = f"{first_order['reason']} ({steps} joint Newton step(s) over orders {orders}{started}; {others})"
    measured_j = probed if probed is not None else jacobian
    blocks = {
        f"{orders[i]}<-{orders[j]}": measured_j[2 * i : 2 * i + 2, 2 * j : 2 * j + 2].tolist()
        for i in range(n)
        for j in range(n)
        if i != j
    }
    return IdentificationResult(
        method="probe-orders",
        harmonic_order=h,
        status=str(first_order["status"]),
        message=message,
        theta_cos=float(best_theta[0]),
        theta_sin=float(best_theta[1]),
        residual=Phasor(float(final_a[0]), float(final_a[1]), final_w.phasor.samples, final_w.phasor.periods),
        uncompensated=before.phasor,
        plant_time_s=session.plant_time_s,
        windows_used=len(history),
        windows_discarded=session.windows_discarded,
        s_model=s_hat,
        target_db=options.target_db,
        noise_floor_db=noise_floor_db(final_w, float(uncompensated[0])),
        details={
            "orders": per_order,
            "newton_steps": steps,
            "probe_deg": [math.degrees(p) for p in probe_rad],
            "jacobian": measured_j.tolist(),
            "jacobian_probed": probed is not None,
            "jacobian_refined": jacobian.tolist(),
            "order_list": orders,
            "prior": None if use is None else use.source,
            "cross_paths": blocks,
            "gamma_limited": limited,
        },
        traces={
            "orders_history": history,
            "orders_history_columns": ["plant_time_s"]
            + [f"theta_{c}_{o}" for o in orders for c in ("cos", "sin")]
            + [f"amplitude_fs_{o}" for o in orders],
            **spectrum_traces(before, final_w),
        },
    )
