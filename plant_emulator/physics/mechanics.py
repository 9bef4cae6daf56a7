"""The mechanical path: shaft, load machine, and the accelerometer's transfer function.

    J dw_m/dt = T_em + T_lm - B w_m                                   (`shaft_acceleration`)
with T_lm the load machine torque: ramped speed reference, PI speed loop plus acceleration
feed-forward (`load_machine`); w_m and the electrical angle phi_e = N_p * integral(w_m) advance by the
trapezoidal rule (`shaft_advance`).

Sensor: alpha_meas = H(z) dw_m/dt + noise, H = J G_Salpha (zero z, poles p, H(0) = 1, section 2.3;
paper: z = -35954, p = -19.6 +- j6746.2 rad/s), bilinear with pre-warping at |p| (`sensor_biquad`),
run in direct form II transposed (`sensor_step`). Units: Nm, rad/s, rad/s^2, kg m^2, s.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .firmware import P_TS

TWO_PI = 2.0 * math.pi

# ---- parameters (indices into p) ----
P_J = 15  # kg m^2
P_B = 16  # Nm/(rad/s), viscous friction
P_H_B0 = 17  # sensor biquad (direct form II transposed), normalised a0 = 1
P_H_B1 = 18
P_H_B2 = 19
P_H_A1 = 20
P_H_A2 = 21
P_NOISE = 23  # rad/s^2, sensor noise standard deviation
P_LOAD_KP = 31  # Nm/(rad/s)
P_LOAD_KI = 32  # Nm/rad
P_LOAD_RAMP = 33  # rad/s^2 (mechanical), ramp of the speed reference
P_LOAD_TMAX = 34  # Nm

# ---- setpoints (indices into sp) ----
S_LOAD_ON = 7  # 1: load machine speed loop active
S_LOAD_SPEED = 8  # rad/s, mechanical target speed of the load machine
S_LOAD_ACCEL = 11  # rad/s^2, the load's ramp away from standstill (0x6083); 0: the scenario's P_LOAD_RAMP
S_LOAD_DECEL = 12  # rad/s^2, its ramp towards standstill (0x6084); 0: the scenario's P_LOAD_RAMP

# ---- state (indices into x) ----
X_PHI_E = 6  # rad, electrical angle in [0, 2 pi)
X_OMEGA_M = 7  # rad/s, mechanical speed
X_LOAD_INT = 8  # Nm, load speed-loop integrator
X_LOAD_REF = 9  # rad/s, ramped speed reference
X_H_S1 = 10  # sensor biquad states
X_H_S2 = 11


@njit(cache=True, inline="always")
def load_machine(load_on, load_ref, load_int, load_target, w_m, ramp_up, ramp_down, kp, ki, j, ts, tmax):
    """One period of the load machine: reference ramped towards load_target by at most `ramp_up` (rad/s
    per period) while it moves away from standstill, `ramp_down` while towards it (CiA 402 profile
    acceleration / deceleration), T_lm = K_p e_w + integral + J d(ref)/dt (the acceleration feed-forward lets the ramp
    run without integrator wind-up), |T_lm| <= tmax with conditional integration. Off: torque-free,
    reference tracking the shaft (bumpless switch-on). Returns (T_lm, ref, integral)."""
    if load_on:
        ref_prev = load_ref
        away = (load_target > load_ref >= 0.0) or (load_target < load_ref <= 0.0)
        ramp = ramp_up if away else ramp_down
        if load_ref < load_target - ramp:
            load_ref += ramp
        elif load_ref > load_target + ramp:
            load_ref -= ramp
        else:
            load_ref = load_target
        e_w = load_ref - w_m
        t_lm = kp * e_w + load_int + j * (load_ref - ref_prev) / ts
        if t_lm > tmax:
            t_lm = tmax
        elif t_lm < -tmax:
            t_lm = -tmax
        else:
            load_int += ki * ts * e_w
    else:
        load_ref = w_m
        load_int = 0.0
        t_lm = 0.0
    return t_lm, load_ref, load_int


@njit(cache=True, inline="always")
def shaft_acceleration(t_em, t_lm, b, w_m, j):
    """dw_m/dt = (T_em + T_lm - B w_m) / J, rad/s^2."""
    return (t_em + t_lm - b * w_m) / j


@njit(cache=True, inline="always")
def shaft_advance(w_m, phi, alpha, n_p, ts):
    """(w_m, phi_e) one period on: w_m + T_s alpha, phi_e by the trapezoidal rule, wrapped to [0, 2 pi)."""
    w_new = w_m + ts * alpha
    phi += n_p * ts * 0.5 * (w_m + w_new)
    if phi >= TWO_PI:
        phi -= TWO_PI
    elif phi < 0.0:
        phi += TWO_PI
    return w_new, phi


@njit(cache=True, inline="always")
def sensor_step(alpha, b0, b1, b2, a1, a2, s1, s2):
    """One sample of the sensor path H(z) in direct form II transposed. Returns (y, s1, s2)."""
    y = b0 * alpha + s1
    s1 = b1 * alpha - a1 * y + s2
    s2 = b2 * alpha - a2 * y
    return y, s1, s2


def sensor_biquad(zero_rad_s: float, pole_re_rad_s: float, pole_im_rad_s: float, ts_s: float):
    """H(s) = J G_Salpha(s) = (w0^2/(-z)) (s - z)/((s - p1)(s - p2)), w0 = |p|, so H(0) = 1
    (section 2.3: z = -35954, p = -19.6 +- j6746.2 rad/s). Bilinear transform pre-warped at w0 so
    the lightly damped resonance lands at the right frequency. Returns (b0, b1, b2, a1, a2)."""
    from scipy.signal import bilinear

    w0_sq = pole_re_rad_s**2 + pole_im_rad_s**2
    w0 = math.sqrt(w0_sq)
    num = np.array([1.0, -zero_rad_s]) * (w0_sq / (-zero_rad_s))
    den = np.array([1.0, -2.0 * pole_re_rad_s, w0_sq])
    # pre-warping: bilinear with the sample rate that maps w0 exactly
    fs_warp = w0 / (2.0 * math.tan(w0 * ts_s / 2.0))
    bz, az = bilinear(num, den, fs=fs_warp)
    bz = np.concatenate([bz, np.zeros(3 - len(bz))]) / az[0]
    az = az / az[0]
    return float(bz[0]), float(bz[1]), float(bz[2]), float(az[1]), float(az[2])


def sensor_response(p: np.ndarray, omega_rad_s: float) -> complex:
    """Frequency response of the discrete sensor path H(e^{j w T_s}) (for tests / calibration)."""
    z = np.exp(1j * omega_rad_s * p[P_TS])
    num = p[P_H_B0] + p[P_H_B1] / z + p[P_H_B2] / z**2
    den = 1.0 + p[P_H_A1] / z + p[P_H_A2] / z**2
    return complex(num / den)
