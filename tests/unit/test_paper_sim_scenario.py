"""The paper-sim scenario (sec. 3.1, eq. 23) and the emulator's oscilloscope, against closed forms."""

import math

import numpy as np
import pytest

from plant_emulator import physics as ph
from plant_emulator import scenario as scn
from plant_emulator.scope import CHANNELS, Scope


def test_paper_sim_disturbance_is_eq_23_alone():
    """d = 40 mNm sin(6 phi_e) at any operating point, no dead-time voltage, a linear machine."""
    p, tab = scn.build(scn.load("paper-sim"))
    assert p[ph.P_SAT_N] == 0 and p[ph.P_T_DEAD] == 0 and p[ph.P_XH_N] == 0
    assert p[ph.P_W_BW] == pytest.approx(2 * math.pi * 1200)
    for torque_nm, speed_rpm in ((4.746, 1000.0), (4.746, 200.0), (1.0, 3000.0)):
        plant = ph.Plant(p, tab)
        plant.init_op(torque_nm, speed_rpm, 12.0)
        sp = ph.new_setpoints(12.0)
        sp[ph.S_POWER], sp[ph.S_TORQUE_NM], sp[ph.S_LOAD_ON] = 1.0, torque_nm, 1.0
        sp[ph.S_LOAD_SPEED] = speed_rpm * 2 * math.pi / 60
        *_, trace = plant.run(sp, 2000, trace=True, frames=False)
        phi = trace[:, ph.TR_PHI_E]
        np.testing.assert_allclose(trace[:, ph.TR_DIST], 0.040 * np.sin(6 * phi), atol=1e-12)
        assert np.all(trace[:, ph.TR_UD_DT] == 0) and np.all(trace[:, ph.TR_UQ_DT] == 0)


def test_scope_records_exactly_the_armed_samples():
    scope = Scope(16000.0)
    with pytest.raises(ValueError, match="not armed"):
        scope.read()
    with pytest.raises(ValueError, match="samples"):
        scope.arm(0)
    scope.arm(5)
    assert scope.recording
    rows = np.arange(3 * ph.N_TRACE, dtype=float).reshape(3, ph.N_TRACE)
    scope.feed(rows)
    assert scope.read() == {"ok": True, "ready": False, "recorded": 3, "samples": 5}
    scope.feed(rows + 100)  # only two more rows are kept
    assert not scope.recording
    reply = scope.read()
    assert reply["ready"] and reply["samples"] == 5 and set(reply["channels"]) == set(CHANNELS)
    expected = np.concatenate([rows, rows[:2] + 100])[:, ph.TR_ID]
    np.testing.assert_array_equal(reply["channels"]["i_d_a"], expected)
    scope.feed(rows)  # a full record ignores more
    assert scope.read()["samples"] == 5
