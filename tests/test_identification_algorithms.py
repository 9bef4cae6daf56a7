"""Adaptive and grid algorithms against a closed-form affine plant (eq. 15): theta* = -theta_d."""
import cmath
import math

import pytest

from affine_plant import AffinePlantSession
from service.identification import AdaptiveOptions, GridOptions, identify_adaptive, identify_grid

S_TRUE = 1.35 * cmath.exp(1j * math.radians(126.5))
THETA_OPT = math.radians(3) * cmath.exp(1j * math.radians(280))     # gamma 3 deg, delta 280 deg
GAMMA_MAX = math.radians(15)


@pytest.mark.parametrize("phase_error_deg", [0.0, 30.0, -45.0])
def test_adaptive_converges_to_minus_theta_d(phase_error_deg):
    session = AffinePlantSession(S_TRUE, -THETA_OPT, noise_fs=1e-3)
    s_hat = S_TRUE * cmath.exp(1j * math.radians(phase_error_deg)) * 1.3
    r = identify_adaptive(session, s_hat, AdaptiveOptions(), GAMMA_MAX)
    assert r.status == "ok" and r.details["converged"]
    assert r.gamma_deg == pytest.approx(3.0, abs=0.02)
    assert r.delta_deg == pytest.approx(280.0, abs=0.5)
    assert r.suppression_db > 40


def test_adaptive_never_sends_more_than_gamma_max():
    # a disturbance that needs 20 deg with a 15 deg limit: clamped, reported as no authority
    theta_opt = math.radians(20) * cmath.exp(1j * math.radians(10))
    session = AffinePlantSession(S_TRUE, -theta_opt)
    r = identify_adaptive(session, S_TRUE, AdaptiveOptions(max_blocks=20), GAMMA_MAX)
    assert max(abs(t) for t in session.sent) <= GAMMA_MAX * (1 + 1e-12)
    assert r.status == "no_authority"
    assert r.gamma_deg == pytest.approx(15.0)


def test_grid_minimum_and_fit():
    session = AffinePlantSession(S_TRUE, -THETA_OPT, noise_fs=1e-3)
    r = identify_grid(session, S_TRUE, GridOptions(), GAMMA_MAX)
    assert r.details["points"] == 360
    assert r.details["minimum"]["gamma_deg"] == pytest.approx(3.0) and r.details["minimum"]["delta_deg"] == pytest.approx(280.0)
    assert r.gamma_deg == pytest.approx(3.0, abs=0.01) and r.delta_deg == pytest.approx(280.0, abs=0.2)
    assert abs(r.s_measured - S_TRUE) / abs(S_TRUE) < 0.01
    assert r.suppression_db > 40


def test_grid_options_reject_bad_ranges():
    with pytest.raises(ValueError, match="gamma_stop_deg"):
        GridOptions(gamma_start_deg=5, gamma_stop_deg=1)
