"""Identification on the emulated bench: accuracy, speed, agreement, robustness, safety.

The service layer runs in this process; plant_emulator runs as its own process (socketcand + pty).
Plant time is DAQ samples / rate. Scenarios: paper-bench and seeded variants of it (the truth drawn
within the scenario's ranges; the service only knows the nominal parameters).
"""

import math

import pytest

from service.bench.run import torque_reached
from service.calibration_service import CalibrationService
from service.identification.session import MeasurementError
from service.model.operating_point import OperatingPoint
from service.runs.identify import identify_at, parse_options
from service.settings import load_settings
from tests.support.bench_rig import emulator_control
from tests.support.operating_points import OP1_POINT as OP1

pytestmark = pytest.mark.e2e
SEEDS = [1, 2, 3, 4, 5]


def _angle_diff_deg(a, b):
    return (a - b + 180.0) % 360.0 - 180.0


class GammaRecorder:
    """Wraps the bench's theta output to record every gamma actually sent to the drive."""

    def __init__(self, bench):
        self.sent_gamma_rad = []
        original = bench.drive.set_injection

        def recording(theta_cos_rad, theta_sin_rad, further=()):
            self.sent_gamma_rad.append(math.hypot(theta_cos_rad, theta_sin_rad))
            return original(theta_cos_rad, theta_sin_rad, further)

        bench.drive.set_injection = recording


def _service(tmp_path, **overrides):
    settings = load_settings(
        environ={}, overrides={"emulator.speedup": 0.0, "server.db_path": str(tmp_path / "id.db"), **overrides}
    )
    return CalibrationService(settings)


def _run(svc, method, op=OP1, **options):
    return identify_at(svc.bench, svc.settings, op, method, parse_options(method, options))


@pytest.fixture(scope="module")
def paper(tmp_path_factory):
    with _service(tmp_path_factory.mktemp("paper")) as svc:
        yield svc


@pytest.fixture(scope="module")
def paper_results(paper):
    return {m: _run(paper, m) for m in ("adaptive", "probe", "grid")}


def test_every_method_suppresses_40_db(paper_results):
    for method, r in paper_results.items():
        assert r.status == "ok", (method, r.message)
        assert r.suppression_db >= 40.0, (method, r.suppression_db)
        assert r.target_db == 40.0 and r.noise_floor_db is not None and r.noise_floor_db < -40.0


OP2 = OperatingPoint(torque_nm=1.3, speed_rpm=3000, udc_v=12)


def test_op2_next_to_the_resonance_reaches_40_db(paper):
    # the paper's OP2: its 6th harmonic (1200 Hz) sits ~125 Hz above the 1074 Hz shaft resonance;
    # the shaft mode each step rings is fitted as a nuisance instead of biasing the phasor
    for method in ("probe", "adaptive"):
        r = _run(paper, method, OP2)
        assert r.status == "ok" and r.suppression_db >= 40.0, (method, r.message)
        assert r.details["resonance"]["learned_from_windows"] >= 1


def test_a_harmonic_at_the_noise_floor_is_not_ok(paper):
    # 0 Nm: the harmonic is tiny and the injection has little authority; whatever the method
    # reaches, it is never stored ok below its target (it was: gamma 0, -0.0 dB, ok)
    r = _run(paper, "adaptive", OperatingPoint(torque_nm=0.0, speed_rpm=2000, udc_v=12))
    if r.status == "ok":
        assert r.suppression_db >= r.target_db
    else:
        assert r.message and r.status in ("below_target", "no_authority", "failed")


def test_adaptive_and_grid_fit_agree(paper_results):
    a, g = paper_results["adaptive"], paper_results["grid"]
    assert abs(a.gamma_deg - g.gamma_deg) <= 0.1
    assert abs(_angle_diff_deg(a.delta_deg, g.delta_deg)) <= 2.0
    minimum = g.details["minimum"]
    for r in (a, g):
        assert abs(minimum["gamma_deg"] - r.gamma_deg) <= 0.25
        assert abs(_angle_diff_deg(minimum["delta_deg"], r.delta_deg)) <= 10.0
    assert len(g.traces["grid"]) == 360


def test_plant_time_to_40_db(paper_results):
    probe, adaptive = paper_results["probe"], paper_results["adaptive"]
    assert probe.details["time_to_40db_s"] is not None and probe.details["time_to_40db_s"] <= 0.6
    assert adaptive.details["time_to_40db_s"] is not None and adaptive.details["time_to_40db_s"] <= 1.5
    assert paper_results["grid"].plant_time_s > 5 * adaptive.plant_time_s


def test_probe_reports_measured_s_against_the_model(paper_results):
    d = paper_results["probe"].details
    assert abs(d["model_phase_error_deg"]) < 60 and abs(d["model_gain_error_db"]) < 6
    s = paper_results["probe"].s_measured
    g = paper_results["grid"].s_measured
    assert abs(s - g) / abs(g) < 0.15  # two independent measurements of S agree


@pytest.mark.parametrize("offset_deg", [60.0, -60.0])
def test_adaptive_converges_with_60_deg_phase_error(paper, offset_deg):
    # the offset is against the true S (measured by the probes), not against the model
    true_phase_error = _run(paper, "probe").details["model_phase_error_deg"]
    r = _run(paper, "adaptive", s_hat_phase_offset_deg=offset_deg - true_phase_error)
    assert not r.details["diverged"] and r.details["converged"], r.message
    assert r.suppression_db >= 40.0


def test_120_deg_phase_error_diverges_safely_and_probe_rescues(paper):
    true_phase_error = _run(paper, "probe").details["model_phase_error_deg"]
    recorder = GammaRecorder(paper.bench)
    # without the online S (which would replace the wrong model first), the law must notice itself
    r = _run(paper, "adaptive", s_hat_phase_offset_deg=120.0 - true_phase_error, s_refine=False)
    assert r.details["diverged"] and r.details["fallback"] == "probe", r.message
    gamma_max = math.radians(paper.settings.identification.gamma_max_deg)
    assert max(recorder.sent_gamma_rad) <= gamma_max * (1 + 1e-6)
    assert r.status == "ok" and r.suppression_db >= 40.0


def test_no_authority_is_reported_with_the_reason(paper):
    r = _run(paper, "adaptive", gamma_max_deg=1.0)  # OP1 needs about 3 deg
    assert r.status == "no_authority"
    assert "gamma_max" in r.message
    r = _run(paper, "probe", gamma_max_deg=1.0)
    assert r.status == "no_authority" and "gamma_max" in r.message


def test_low_speed_reaches_target_with_the_drive_decoupling(paper):
    # sec. 2.4: at 500 rpm the 6th harmonic (200 Hz) sits near the nominal current loop's 160 Hz, which
    # counteracts the injection: without decoupling the same cancellation needs a far larger gamma
    # (up to gamma_max) or is not reached; with 0x2000:6 on, both methods meet the target
    low = OperatingPoint(torque_nm=5.0, speed_rpm=500, udc_v=12)
    coupled = _run(paper, "probe", low, decoupling=False)
    assert coupled.details["decoupling"] is False
    if coupled.status != "ok":
        assert "enable decoupling" in coupled.message, coupled.message
    for method in ("probe", "adaptive"):
        decoupled = _run(paper, method, low, decoupling=True)
        assert decoupled.status == "ok" and decoupled.suppression_db >= 40.0, (method, decoupled.message)
        assert decoupled.details["decoupling"] is True
        # seen: 4.7 deg decoupled against 10-15 deg (gamma_max) without
        assert math.hypot(decoupled.theta_cos, decoupled.theta_sin) < 0.7 * math.hypot(
            coupled.theta_cos, coupled.theta_sin
        )


def test_settling_on_the_data_without_sync_line(tmp_path, paper_results):
    # the emulator's fast mode buffers about 1 s of plant time between the plant and the reader
    with _service(tmp_path, **{"daq.sync_input": False, "daq.no_sync_settle_s": 1.5}) as svc:
        r = _run(svc, "probe")
    ref = paper_results["probe"]
    assert r.status == "ok" and r.suppression_db >= 40.0
    assert abs(r.gamma_deg - ref.gamma_deg) <= 0.1 and abs(_angle_diff_deg(r.delta_deg, ref.delta_deg)) <= 2.0


# operating points whose 6th harmonic (800, 600, 400 Hz) stays clear of the shaft resonance
# (1074 Hz nominal, drawn within +-10 % by the seed): closer, the sensor goes over range
SEEDED_OPS = [
    OP1,
    OperatingPoint(torque_nm=4.0, speed_rpm=1500, udc_v=12),
    OperatingPoint(torque_nm=1.5, speed_rpm=1000, udc_v=12),
]


@pytest.mark.parametrize("seed", SEEDS)
def test_seeded_scenarios(tmp_path, seed):
    ops = SEEDED_OPS
    with _service(tmp_path, **{"emulator.seed": seed}) as svc:
        for op in ops:
            a = _run(svc, "adaptive", op)
            p = _run(svc, "probe", op)
            for r in (a, p):
                # honest: ok means the target was met; anything else says why
                if r.status != "ok":
                    assert r.status in ("no_authority", "below_target") and r.message, (seed, op, r.method)
                    continue
                assert r.suppression_db >= r.target_db, (seed, op, r.method, r.suppression_db)
            if a.status == p.status == "ok":
                # both stopped once their residual was 40 dB down: the same optimum, not the same
                # point (where the path responds weakly in one direction, as at low speed, theta may
                # differ along it by several % at the same residual): within 10 % of |theta*|
                apart_rad = abs(complex(a.theta_cos - p.theta_cos, a.theta_sin - p.theta_sin))
                allowed_rad = 0.1 * math.hypot(p.theta_cos, p.theta_sin)
                assert apart_rad <= allowed_rad, (seed, op, math.degrees(apart_rad), math.degrees(allowed_rad))
        g = _run(svc, "grid")
        a = _run(svc, "adaptive")
        assert abs(a.gamma_deg - g.gamma_deg) <= 0.1 and abs(_angle_diff_deg(a.delta_deg, g.delta_deg)) <= 2.0
        assert abs(g.details["minimum"]["gamma_deg"] - a.gamma_deg) <= 0.25
        assert abs(_angle_diff_deg(g.details["minimum"]["delta_deg"], a.delta_deg)) <= 10.0


def test_a_line_beating_with_the_harmonic_settles_on_longer_blocks(paper):
    """At 1 Nm, 2350 rpm the paper bench's accelerometer carries a line at ~960 Hz beside the 6th
    harmonic at 940 Hz (found in a recording's spectrum: the 96th electrical order folded by the 16 kHz
    sampling), so the h-th phasor beats at ~20 Hz by ~1 % of itself: on 10 ms blocks it never looked
    steady and the point failed after 20 s of plant time. The settling lengthens its blocks when the
    phasor keeps moving (a beat averages out; a drift would show more), and the point is identified
    in line with its neighbours 10 rpm either side (theta turns ~0.7 deg/rpm here)."""
    results = {
        n: _run(paper, "probe", OperatingPoint(torque_nm=1.0, speed_rpm=n, udc_v=12.0)) for n in (2340, 2350, 2360)
    }
    assert all(r.status == "ok" for r in results.values()), {n: r.message for n, r in results.items()}
    lo, mid, hi = (results[n].delta_deg for n in (2340, 2350, 2360))
    expected = lo + _angle_diff_deg(hi, lo) / 2.0
    assert abs(_angle_diff_deg(mid, expected)) < 3.0, (lo, mid, hi)


def test_a_point_the_machine_cannot_reach_fails_with_the_drives_torque(tmp_path):
    """Seed 1's machine has ~18 % more magnet flux than the nominal: at 12 V it runs out of voltage
    before 3200 rpm, where the current controller sits in its limit and the motor brakes against a
    +2.5 Nm command. The point fails saying so (the drive's torque actual), instead of a theta
    calibrated at an operating point the motor does not run at; a point it reaches is still ok."""
    with _service(tmp_path, **{"emulator.seed": 1}) as svc:
        with pytest.raises(MeasurementError, match="does not reach 2.5 Nm here: its torque actual reads -"):
            _run(svc, "probe", OperatingPoint(torque_nm=2.5, speed_rpm=3200, udc_v=12.0))
        within = _run(svc, "probe", OperatingPoint(torque_nm=2.5, speed_rpm=2000, udc_v=12.0))
    assert within.status == "ok", within.message


@pytest.mark.parametrize(
    "command_nm, actual_nm, reached",
    [(2.5, 2.0, True), (2.5, 1.3, True), (2.5, 1.2, False), (2.5, -2.2, False), (-2.0, -1.5, True), (0.1, -0.1, True)],
)
def test_torque_reached_is_half_the_command_with_its_sign(command_nm, actual_nm, reached):
    assert torque_reached(command_nm, actual_nm) is reached


def test_every_setpoint_of_a_run_is_checked_on_its_one_way_down(paper):
    """A run's commands (service/bench/run_commands.py) refuse, before anything is sent, a setpoint outside
    the hard limits, a gamma above the run's gamma_max and a mode the drive does not have: the drive's
    setpoint count does not move."""
    from service.model.limits import LimitError

    bench = paper.bench
    with bench.run(6, gamma_max_rad=math.radians(2.0)) as run:
        commands = run.commands
        written = bench.setpoints_written()
        refusals = [
            (lambda: commands.send_theta(math.radians(3.0), 0.0), "gamma_max"),
            (lambda: commands.send_theta(float("nan"), 0.0), "not finite"),
            (lambda: commands.set_torque_nm(99.0), "torque_nm 99"),
            (lambda: commands.set_speed_rpm(1e9), "speed_rpm"),
            (lambda: commands.set_dc_link(1000.0), "udc_v"),
            (lambda: commands.send_injection_mode("on"), "injection mode"),
        ]
        for command, what in refusals:
            with pytest.raises(LimitError, match=what):
                command()
        assert bench.setpoints_written() == written
        assert commands.theta is None and commands.torque_nm is None  # nothing was told
    assert bench.status()["drive"]["state"] != "OPERATION_ENABLED"


def test_several_orders_are_cancelled_jointly_on_the_bench(paper):
    """probe-orders at OP1 on paper-bench, whose 12th is its own: both orders ok at 40 dB, each judged on its
    own; the drive took the 12th through 0x2002 (the control socket shows it in force during the run) and was
    left with injection off and no further order after it; the cross-paths measured, not zero."""
    seen = []
    original = paper.bench.drive.set_injection

    def recording(theta_cos_rad, theta_sin_rad, further=()):
        seen.append(tuple(further))
        return original(theta_cos_rad, theta_sin_rad, further)

    paper.bench.drive.set_injection = recording
    try:
        result = _run(paper, "probe-orders", orders=[6, 12])
    finally:
        paper.bench.drive.set_injection = original
    by_order = {o["order"]: o for o in result.details["orders"]}
    assert list(by_order) == [6, 12]
    for o in by_order.values():
        assert o["status"] != "ok" or o["suppression_db"] >= o["target_db"], o  # never ok below its target
    assert by_order[6]["status"] == "ok" and by_order[6]["suppression_db"] >= 40.0, by_order[6]
    assert by_order[12]["suppression_db"] >= 30.0, by_order[12]  # measured 37-55 dB at OP1 (0.4 s windows)
    assert result.status == by_order[6]["status"] and result.theta_cos == by_order[6]["theta_cos"]
    assert any(f and f[0][0] == 12 for f in seen)  # the 12th went to the drive as a further order
    assert max(abs(v) for row in result.details["cross_paths"]["12<-6"] for v in row) > 0
    status = emulator_control(paper.emulator.endpoints, {"status": True})["faults"]
    assert status["drive_injection_mode"] == 0 and status["drive_further_theta_rad"] == []


def test_a_12th_under_the_sensors_noise_is_said_not_confirmable(paper):
    """At 2.5 Nm / 2600 rpm paper-bench's 12th is some 4e-4 of full scale beside a 6th of 0.85: its 40 dB target
    (4e-6 fs) lies far within the noise of the longest window (1e-5 fs at 1.2 s). The 6th is ok; the 12th is not,
    saying why from the run's own reference, never ok below its target; the drive is left with no injection."""
    op = OperatingPoint(torque_nm=2.5, speed_rpm=2600, udc_v=12)
    result = _run(paper, "probe-orders", op=op, orders=[6, 12])
    by_order = {o["order"]: o for o in result.details["orders"]}
    assert by_order[6]["status"] == "ok" and by_order[6]["suppression_db"] >= by_order[6]["target_db"], by_order[6]
    assert by_order[12]["status"] == "below_target", by_order[12]
    assert "not confirmable here" in by_order[12]["reason"], by_order[12]["reason"]
    status = emulator_control(paper.emulator.endpoints, {"status": True})["faults"]
    assert status["drive_injection_mode"] == 0 and status["drive_further_theta_rad"] == []
