"""Computed order tracking (service/model/order_tracking.py) against closed forms on synthetic ramps.

The ramps (tests/support/runup_ramp.py): speed n0 -> n1 linear, 4 pole pairs, 16 kHz, the electrical
angle integrated exactly and handed over wrapped to [0, 2 pi) as the DAQ gives it; an order h of amplitude
a and phase psi is A = a e^{j psi} = a_c - j a_s (docs/conventions.md, Phasors).

Tolerances. Noise sigma = 0.005 fs per sample, tones of 0.1 fs; a 10 rpm bin of the 100 rpm/s ramp holds
0.1 s = 1600 samples, the end bins half of that, in whole windows (~960 samples at 1000 rpm): each phasor
component has sd sigma sqrt(2/N) = 1.8e-4 fs (2.3e-4 in a one-window end bin), 0.18 % of the amplitude and
0.1 deg of phase (0.23 %, 0.13 deg): 2 % and 1 deg are more than 7 sd of the worst bin (seeds 1-8 gave at
most 0.8 % and 0.42 deg; the seed is fixed).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.model.demodulation import ResonanceMode
from service.model.harmonic import phasor
from service.model.order_tracking import OrderTrack, contiguous_runs, prominent_orders, track_orders, window_bounds
from tests.support import runup_ramp
from tests.support.runup_ramp import POLE_PAIRS, RATE_HZ, ramp_angle, tone

NOISE_FS = 0.005
TONES = {6: (0.1, 30.0), 12: (0.1, -120.0)}


def speed_at(t: np.ndarray, n0_rpm: float, n1_rpm: float, duration_s: float) -> np.ndarray:
    return n0_rpm + (n1_rpm - n0_rpm) * t / duration_s


def wrap_deg(x: np.ndarray) -> np.ndarray:
    return (x + 180.0) % 360.0 - 180.0


def ramp_record(n0: float, n1: float, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """16 s ramp with order 6 (0.1 fs, 30 deg), order 12 (0.1 fs, -120 deg) and white noise."""
    return runup_ramp.ramp_record(n0, n1, TONES, NOISE_FS, seed=seed)


@pytest.mark.parametrize(("n0", "n1"), [(1000.0, 2600.0), (2600.0, 1000.0)], ids=["up", "down"])
def test_ramp_orders_within_two_percent_and_one_degree_per_bin(n0: float, n1: float) -> None:
    angle, alpha = ramp_record(n0, n1)
    track = track_orders(angle, alpha, RATE_HZ, POLE_PAIRS, [6, 12])
    assert np.all(np.diff(track.speed_rpm) <= 10.0 + 1e-9)
    assert track.speed_rpm[0] == pytest.approx(1000.0) and track.speed_rpm[-1] == pytest.approx(2600.0)
    assert np.all(track.windows > 0)
    for row, (amplitude, phase) in enumerate([(0.1, 30.0), (0.1, -120.0)]):
        assert np.max(np.abs(track.amplitude_fs[row] / amplitude - 1.0)) < 0.02
        assert np.max(np.abs(wrap_deg(track.phase_deg[row] - phase))) < 1.0


def test_phasor_is_harmonic_phasor_at_constant_speed() -> None:
    """Same a_c, a_s and sign as service/model/harmonic.phasor over the same whole periods."""
    _, phi = ramp_angle(1500.0, 1500.0, 0.5)
    alpha = tone(phi, 6, 0.2, 75.0) + tone(phi, 12, 0.05, -10.0)
    angle = np.mod(phi, 2 * math.pi)
    track = track_orders(angle, alpha, RATE_HZ, POLE_PAIRS, [6, 12])
    assert list(track.speed_rpm) == [1500.0]
    for row, order in enumerate([6, 12]):
        reference = phasor(alpha, angle, order, 4 * order)
        assert track.phasor[row, 0] == pytest.approx(reference.complex, abs=1e-6)
    assert track.phase_deg[0, 0] == pytest.approx(75.0, abs=1e-3)
    assert track.amplitude_fs[0, 0] == pytest.approx(0.2, rel=1e-5)
    unwrapped = track_orders(phi, alpha, RATE_HZ, POLE_PAIRS, [6, 12])  # the angle unwrapped already: the same
    np.testing.assert_allclose(unwrapped.phasor, track.phasor, rtol=1e-9)


def test_order_amplitude_that_changes_with_speed_is_tracked() -> None:
    t, phi = ramp_angle(1000.0, 2600.0, 16.0)
    speed = speed_at(t, 1000.0, 2600.0, 16.0)

    def amplitude_of(n_rpm: np.ndarray) -> np.ndarray:  # a resonance-like bump over the ramp
        return 0.05 + 0.1 * np.exp(-(((n_rpm - 1800.0) / 300.0) ** 2))

    rng = np.random.default_rng(2)
    alpha = tone(phi, 6, amplitude_of(speed), 45.0) + rng.normal(0.0, NOISE_FS, len(t))
    track = track_orders(np.mod(phi, 2 * math.pi), alpha, RATE_HZ, POLE_PAIRS, [6])
    truth = amplitude_of(track.speed_rpm)
    # within a bin the amplitude moves by at most 5 rpm * max slope (0.1 * sqrt(2/e) / 300 per rpm): 1e-3 fs
    assert np.max(np.abs(track.amplitude_fs[0] - truth) / truth) < 0.03
    assert np.max(np.abs(wrap_deg(track.phase_deg[0] - 45.0))) < 1.5


def test_noise_floor_is_the_rms_amplitude_of_an_order_without_a_tone() -> None:
    """Order 9 carries no tone: its amplitudes over the bins are Rayleigh with rms = the noise floor.
    The floor itself, from sigma: 2 sigma / sqrt(N) for K windows of N/K samples (docs of the module).
    Factors: each window's noise estimate is the median of 45-120 bins between the orders (sd of the
    variance ~1.25 / sqrt(M): 11-19 %), pooled over the 1-4 windows of a bin, so one bin's floor has an sd
    of ~5-9 %: 1.6 for every bin is > 5 sd, and 1.25 for their median far more; the rms of 161 Rayleigh
    amplitudes (mean square sd 1 / sqrt(161) = 8 %, 4 % on the rms) around the floor: 1.25 is > 5 sd.
    Seeds 1-8 gave medians 0.98-1.00, bins 0.79-1.24, rms 0.89-1.08."""
    angle, alpha = ramp_record(1000.0, 2600.0, seed=3)
    track = track_orders(angle, alpha, RATE_HZ, POLE_PAIRS, [6, 9, 12])
    full = track.windows >= np.median(track.windows)
    samples_per_bin = 0.1 * RATE_HZ  # 10 rpm at 100 rpm/s
    expected = 2.0 * NOISE_FS / math.sqrt(samples_per_bin)
    ratio = track.noise_floor_fs[full] / expected
    assert 1 / 1.25 < np.median(ratio) < 1.25
    assert np.all((ratio > 1 / 1.6) & (ratio < 1.6))
    rms_order9 = math.sqrt(np.mean(track.amplitude_fs[1] ** 2 / track.noise_floor_fs**2))
    assert 1 / 1.25 < rms_order9 < 1.25


def test_window_across_a_gap_is_skipped() -> None:
    """2000 samples lost mid-ramp: the angle jumps by an unknown number of turns there; every bin still
    holds the truth, no window starts before and ends after the gap, and the gap costs only the two
    partial windows at its sides."""
    angle, alpha = ramp_record(1000.0, 2600.0, seed=4)
    lost = slice(80_000, 82_000)
    keep = np.ones(len(angle), bool)
    keep[lost] = False
    gap_before = np.zeros(int(keep.sum()), bool)
    gap_before[lost.start] = True
    angle_gap, alpha_gap = angle[keep], alpha[keep]
    track = track_orders(angle_gap, alpha_gap, RATE_HZ, POLE_PAIRS, [6, 12], gap_before=gap_before)
    populated = track.windows > 0
    for row, (amplitude, phase) in enumerate([(0.1, 30.0), (0.1, -120.0)]):
        assert np.max(np.abs(track.amplitude_fs[row][populated] / amplitude - 1.0)) < 0.02
        assert np.max(np.abs(wrap_deg(track.phase_deg[row][populated] - phase))) < 1.0
    runs = contiguous_runs(angle_gap, gap_before)
    assert [first for first, _ in runs] == [0, lost.start]
    for first, run in runs:
        assert all(first + stop <= len(angle_gap) for _, stop in window_bounds(run, 4))
    whole = track_orders(angle, alpha, RATE_HZ, POLE_PAIRS, [6, 12])
    _, phi = ramp_angle(1000.0, 2600.0, 16.0)
    lost_turns = (phi[lost.stop] - phi[lost.start]) / (2 * math.pi)
    assert whole.windows.sum() - lost_turns / 4 - 2 <= track.windows.sum() <= whole.windows.sum() - lost_turns / 4 + 1


def test_high_order_is_exact_where_interpolation_would_not_be() -> None:
    """Order 40 at 2200 rpm (f_h = 5.9 kHz, 2.7 samples per cycle): the fit at the sample angles holds it;
    the resampling alternative the module doc names loses ~40 % there."""
    _, phi = ramp_angle(2195.0, 2205.0, 0.2)
    alpha = tone(phi, 40, 0.1, 20.0)
    track = track_orders(np.mod(phi, 2 * math.pi), alpha, RATE_HZ, POLE_PAIRS, [6, 40])
    assert track.amplitude_fs[1, 0] == pytest.approx(0.1, rel=1e-3)
    assert track.phase_deg[1, 0] == pytest.approx(20.0, abs=0.1)


def test_orders_beyond_the_sample_rate_read_nan() -> None:
    angle, alpha = ramp_record(1000.0, 2600.0, seed=5)
    track = track_orders(angle, alpha, RATE_HZ, POLE_PAIRS, [6, 48])
    # order 48 reaches 0.4 f_s at 6400 / (48 * 4 / 60) = 2000 rpm
    assert np.all(np.isfinite(track.amplitude_fs[1][track.speed_rpm < 1990.0]))
    assert np.all(np.isnan(track.amplitude_fs[1][track.speed_rpm > 2010.0]))


def test_shaft_ring_is_removed_as_a_nuisance() -> None:
    """A ring of the shaft mode (1074 Hz, tau 51 ms, the paper's) set off at the ramp's start: with the mode
    fitted, the first bins hold the truth; without, order 12 near the ring's frequency is off."""
    mode = ResonanceMode(sigma_rad_s=-1.0 / 0.051, omega_rad_s=2 * math.pi * 1074.0)
    t, phi = ramp_angle(1300.0, 1400.0, 1.0)
    ring = 0.5 * np.exp(mode.sigma_rad_s * t) * np.cos(mode.omega_rad_s * t + 0.3)
    alpha = tone(phi, 6, 0.1, 30.0) + tone(phi, 12, 0.1, -120.0) + ring
    angle = np.mod(phi, 2 * math.pi)
    with_mode = track_orders(angle, alpha, RATE_HZ, POLE_PAIRS, [6, 12], mode=mode)
    assert np.max(np.abs(with_mode.amplitude_fs / 0.1 - 1.0)) < 1e-3
    without = track_orders(angle, alpha, RATE_HZ, POLE_PAIRS, [6, 12])
    assert np.max(np.abs(without.amplitude_fs / 0.1 - 1.0)) > 0.02


def test_refuses_bad_arguments() -> None:
    angle, alpha = ramp_record(1000.0, 1100.0)
    with pytest.raises(ValueError, match="orders"):
        track_orders(angle, alpha, RATE_HZ, POLE_PAIRS, [0])
    with pytest.raises(ValueError, match="bin width"):
        track_orders(angle, alpha, RATE_HZ, POLE_PAIRS, [6], bin_width_rpm=0.0)
    with pytest.raises(ValueError, match="periods"):
        track_orders(angle, alpha, RATE_HZ, POLE_PAIRS, [6], window_periods=2)
    with pytest.raises(ValueError, match="no whole window"):
        track_orders(angle[:10], alpha[:10], RATE_HZ, POLE_PAIRS, [6])


def test_an_order_crossing_the_sensor_resonance_leaks_into_an_order_fitted_without_it() -> None:
    """Why a validation's run-ups fit the whole survey (service/runs/runup_validation.py): the injection's own
    12th, swept through the accelerometer's lightly damped resonance (section 2.3's pole, 1074 Hz: at 1340 rpm
    with 4 pole pairs), changes within a window faster than any order's constant phasor; fitted only for the
    6th, it read as a 6th several times the true one (paper-bench's run-ups failed at 1330-1350 rpm at every
    torque). The truth: the 6th through the same resonance, |H| = 1 / |1 - (w_6 / w_r)^2| (the zero far away)."""
    from scipy.signal import bilinear, lfilter

    sigma, omega_r = -19.6, 6746.2  # rad/s, the paper's sensor pole
    b, a = bilinear([sigma**2 + omega_r**2], [1.0, -2.0 * sigma, sigma**2 + omega_r**2], fs=RATE_HZ)
    _, phi = ramp_angle(1200.0, 1500.0, 1.5)  # 200 rpm/s, the validation's rate
    alpha = lfilter(b, a, tone(phi, 6, 2e-4, 50.0) + tone(phi, 12, 1e-3, 60.0))
    alpha += np.random.default_rng(1).normal(0.0, 3e-4, len(phi))
    mode = ResonanceMode(sigma_rad_s=sigma, omega_rad_s=omega_r)
    errors = []
    for orders in ([6], list(range(1, 49))):
        track = track_orders(np.mod(phi, 2 * math.pi), alpha, RATE_HZ, POLE_PAIRS, orders, mode=mode)
        w_6 = 6 * POLE_PAIRS * track.speed_rpm / 60.0 * 2.0 * math.pi
        truth = 2e-4 / np.abs(1.0 - (w_6 / omega_r) ** 2)
        errors.append(float(np.max(np.abs(track.amplitude_fs[track.orders.index(6)] - truth))))
    alone, surveyed = errors
    assert alone > 2.0 * 2.7e-4, errors  # fitted alone: off by more than twice the true 6th at the crossing
    assert surveyed < 0.5 * alone, errors  # measured 5.9 times smaller (3.4-6.0 over seeds and 12th levels)


def test_orders_listed_are_those_above_the_floor_over_the_range() -> None:
    """prominent_orders: at least level_db above the bin's floor in at least a quarter of the fitted bins,
    largest first; a one-bin resonance crossing, an order under the level and an order never fitted are not."""
    speed = np.arange(1000.0, 1100.0, 10.0)
    floor = np.full(10, 1e-4)
    amplitude = np.array(
        [
            np.full(10, 1e-2),  # order 6: 40 dB above everywhere
            np.linspace(1e-3, 3e-3, 10),  # order 12: 20.0 .. 29.5 dB
            np.full(10, 5e-4),  # order 18: 14 dB, under the level
            np.where(np.arange(10) == 4, 1e-1, 1e-4),  # order 24: one bin (a resonance crossing)
            np.full(10, np.nan),  # order 40: never fitted
        ]
    )
    track = OrderTrack(speed, (6, 12, 18, 24, 40), amplitude, np.zeros_like(amplitude), floor, np.ones(10, int), 10.0)
    listed = prominent_orders(track, level_db=20.0)
    assert [p.order for p in listed] == [6, 12]
    six, twelve = listed
    assert six.median_above_floor_db == pytest.approx(40.0) and six.fraction_above == 1.0
    assert twelve.max_amplitude_fs == pytest.approx(3e-3) and twelve.at_speed_rpm == 1090.0
    assert twelve.median_above_floor_db == pytest.approx(np.median(20 * np.log10(amplitude[1] / 1e-4)))
    # the level decides: at 10 dB the 18th is there too; at 45 dB nothing is
    assert [p.order for p in prominent_orders(track, level_db=10.0)] == [6, 12, 18]
    assert prominent_orders(track, level_db=45.0) == []
