"""The drive's limit on the injection of several orders at once (manufacturer record 0x2000:5 gamma_max,
docs/interfaces.md): v_inj = sum_k gamma_k cos(h_k phi_e + delta_k) peaks at sum_k gamma_k, so every order's
theta is scaled by one factor that brings the sum of |theta_k| down to gamma_max (eq. 2-4: |u_dq*| = |u_dq|
holds for any angle; the limit keeps the angle small). One order: |theta| <= gamma_max.

The one statement of the rule in Python: the emulated firmware applies it, the identification of several
orders predicts it; the C header's reference decoder carries it for the firmware (service/maps/lut_export.py)."""

from __future__ import annotations

from collections.abc import Iterable


def injection_scale(gammas_rad: Iterable[float], gamma_max_rad: float) -> float:
    """The factor on every order's theta: gamma_max / sum(gammas) where the sum exceeds gamma_max, else 1."""
    total = sum(gammas_rad)
    return gamma_max_rad / total if total > gamma_max_rad and total > 0.0 else 1.0
