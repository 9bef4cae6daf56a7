"""Secondary path S: injection theta (rad) -> h-th harmonic phasor of the measured acceleration.

Model (paper eq. 14-20; docs/conventions.md, Secondary path), evaluated at w = h*omega_e:

    S(jw) = G_Salpha(jw) * G_EM,m * (jw I - A)^-1 B * exp(-jw T_d) * G_comp
    G_comp = [-u_q, u_d]^T                    (eq. 10, V per rad of injection angle)
    G_d    = exp(-jw T_d)                     (eq. 17, T_d = delay_periods / f_ctrl)
    A, B   from R_s, L_d, L_q, omega_e        (eq. 18), G_EM,e = (sI - A)^-1 B (eq. 19)
    G_EM,m = [0, k_T], k_T = 1.5 N_p psi_p    (eq. 20, Nm/A)
    G_Salpha(s) = (1/J) * (w0^2 / -z) * (s - z) / ((s - p1)(s - p2)),  G_Salpha(0) = 1/J
                 (zero z, poles p1,2 identified on the bench, paper sec. 2.3; rad/s^2 per Nm)

S is returned in units of sensor full scale per rad (the DAQ reports alpha / full scale).

Two extensions of the paper's model (both reduce to eq. 14-20 where the paper's assumptions hold):
- G_EM,m is the small-signal torque gain [1.5 N_p (L_d - L_q) i_q, 1.5 N_p (psi_p + (L_d - L_q) i_d)],
  which is eq. 20's [0, k_T] for L_d = L_q;
- current_loop=True closes the nominal PI current control (K_p = w_bw L, K_i = w_bw R_s, the same
  delay) around the machine, G_EM,e -> (I + G_EM,e e^{-sT_d} C(s))^-1 G_EM,e: what the injected harmonic
  sees on a drive WITHOUT decoupling (paper sec. 2.4: the nominal control counteracts the injection).
  Without it the model is 20-60 deg off such a drive at 400-800 Hz; with decoupling (sec. 3.1) the
  nominal control does not see the injected currents and eq. 14-20 holds as written.

Complex form used throughout the service: with Theta = theta_cos - j*theta_sin = gamma*exp(j*delta)
and A = a_c - j*a_s (the harmonic phasor, docs/conventions.md, Phasors), the steady state (eq. 15) is
    A = S * (Theta_d + Theta),
which is the 2x2 real form a = S_ss (theta_d + theta) with S_ss = [[S_r, S_i], [-S_i, S_r]].
"""

from __future__ import annotations

import cmath
import math

import numpy as np

from service.model.operating_point import OperatingPoint, SteadyState, nominal_steady_state
from service.settings import Settings


def g_salpha(
    s: complex, inertia_kg_m2: float, zero_rad_s: float, pole_re_rad_s: float, pole_im_rad_s: float
) -> complex:
    """Torque -> angular acceleration (rad/s^2 per Nm), second order with one zero, unit DC gain * 1/J."""
    p1 = complex(pole_re_rad_s, pole_im_rad_s)
    p2 = p1.conjugate()
    w0_sq = abs(p1) ** 2
    return (1.0 / inertia_kg_m2) * (w0_sq / -zero_rad_s) * (s - zero_rad_s) / ((s - p1) * (s - p2))


def model_secondary_path(
    settings: Settings,
    op: OperatingPoint,
    harmonic_order: int,
    steady: SteadyState | None = None,
    current_loop: bool = False,
    resonance_pole: complex | None = None,
) -> complex:
    """S(j h omega_e) of eq. 14 in full-scale units per rad, from the nominal parameters; the shaft
    pole of G_Salpha from `resonance_pole` (rad/s, as learned on the bench) instead of the settings'."""
    motor, ctrl, mech = settings.motor, settings.control, settings.mechanics
    pole_re, pole_im = (
        (mech.pole_re_rad_s, mech.pole_im_rad_s)
        if resonance_pole is None
        else (resonance_pole.real, resonance_pole.imag)
    )
    steady = steady or nominal_steady_state(op, motor)
    w = harmonic_order * steady.omega_e_rad_s
    s = 1j * w
    a = np.array(
        [
            [-motor.r_s_ohm / motor.l_d_h, steady.omega_e_rad_s * motor.l_q_h / motor.l_d_h],
            [-steady.omega_e_rad_s * motor.l_d_h / motor.l_q_h, -motor.r_s_ohm / motor.l_q_h],
        ]
    )
    b = np.diag([1.0 / motor.l_d_h, 1.0 / motor.l_q_h])
    g_em_e = np.linalg.solve(s * np.eye(2) - a, b)  # eq. 19
    t_d = ctrl.delay_periods / ctrl.control_rate_hz  # eq. 17
    if current_loop:
        w_bw = 2.0 * math.pi * ctrl.bandwidth_hz
        c = np.diag([w_bw * motor.l_d_h + w_bw * motor.r_s_ohm / s, w_bw * motor.l_q_h + w_bw * motor.r_s_ohm / s])
        g_em_e = np.linalg.solve(np.eye(2) + g_em_e @ c * cmath.exp(-s * t_d), g_em_e)
    reluctance = motor.l_d_h - motor.l_q_h
    g_em_m = (
        1.5 * motor.pole_pairs * np.array([reluctance * steady.i_q_a, motor.psi_p_vs + reluctance * steady.i_d_a])
    )  # eq. 20 for L_d = L_q
    g_comp = np.array([-steady.u_q_v, steady.u_d_v])  # eq. 10
    torque_per_rad = g_em_m @ g_em_e @ g_comp * cmath.exp(-s * t_d)
    alpha_per_rad = g_salpha(s, mech.inertia_kg_m2, mech.zero_rad_s, pole_re, pole_im) * torque_per_rad
    return complex(alpha_per_rad) / settings.daq.accel_full_scale_rad_s2


def s_matrix(s: complex) -> np.ndarray:
    """2x2 real form S_ss = [[S_r, S_i], [-S_i, S_r]] mapping theta to [a_c, a_s]
    (docs/conventions.md, Secondary path)."""
    return np.array([[s.real, s.imag], [-s.imag, s.real]])


def rotation_part(s_ss: np.ndarray) -> complex:
    """The complex gain S nearest (least squares) to a measured 2x2 S_ss; inverse of s_matrix where
    S_ss has the rotation form: S = (S11 + S22)/2 + j (S12 - S21)/2."""
    return complex((s_ss[0, 0] + s_ss[1, 1]) / 2, (s_ss[0, 1] - s_ss[1, 0]) / 2)


def theta_complex(theta_cos: float, theta_sin: float) -> complex:
    """Theta = theta_cos - j theta_sin = gamma * exp(j delta) (eq. 21-22)."""
    return complex(theta_cos, -theta_sin)


def theta_parts(theta: complex) -> tuple[float, float]:
    """(theta_cos, theta_sin) of the complex Theta."""
    return theta.real, -theta.imag


def gamma_delta(theta_cos: float, theta_sin: float) -> tuple[float, float]:
    """gamma = |theta| (eq. 21), delta = -atan2(theta_sin, theta_cos) in [0, 2 pi) (eq. 22); radians."""
    return math.hypot(theta_cos, theta_sin), (-math.atan2(theta_sin, theta_cos)) % (2.0 * math.pi)


def theta_from_gamma_delta(gamma_rad: float, delta_rad: float) -> tuple[float, float]:
    """Inverse of eq. 21-22: theta_cos = gamma cos(delta), theta_sin = -gamma sin(delta)."""
    return gamma_rad * math.cos(delta_rad), -gamma_rad * math.sin(delta_rad)


def phase_error_deg(s_hat: complex, s_true: complex) -> float:
    """Phase of S_hat against S, wrapped to (-180, 180] degrees."""
    return math.degrees(cmath.phase(s_hat / s_true))
