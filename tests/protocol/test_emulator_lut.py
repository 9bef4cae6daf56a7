"""Drive firmware (in process, no CAN): LUT download, CRC and map id read-back, refusal of bad images,
LUT-mode injection = interpolated theta (format version 3: polar and cartesian, filled cells, non-uniform
axes; a version 2 image still taken), the eq. 11 switch 0x2000:8."""

from __future__ import annotations

import math
import struct
import zlib

import canopen
import numpy as np
import pytest

from drivers import DRIVE_EDS, lut_image
from drivers.cia402 import State402
from plant_emulator import physics as ph
from plant_emulator import scenario as scn
from plant_emulator.drive_firmware import DriveFirmware

T_AX = [1.0, 2.5, 4.0]
N_AX = [1000.0, 2000.0]
U_AX = [12.0]


@pytest.fixture()
def drive():
    d = DriveFirmware(canopen.Network(), 5, str(DRIVE_EDS))
    d.state = State402.OPERATION_ENABLED
    return d


def write(d, index, sub, value):
    od = d.node.object_dictionary
    obj = od[index] if sub == 0 else od[index][sub]
    d.node.set_data(index, sub, obj.encode_raw(value) if not isinstance(value, bytes) else value, check_writable=True)


def read(d, index, sub):
    od = d.node.object_dictionary
    return od[index][sub].decode_raw(d.node.get_data(index, sub))


def image(scale=1.0, valid=None, h=6, map_id=3, interpolation="cartesian"):
    """An image whose thetas the tests' expectations interpolate by hand (cartesian unless told)."""
    tc = scale * np.arange(6, dtype=float).reshape(1, 2, 3) * 0.01
    ts = -scale * np.arange(6, dtype=float)[::-1].reshape(1, 2, 3) * 0.005
    return lut_image.encode(h, T_AX, N_AX, U_AX, tc, ts, valid, map_id=map_id, interpolation=interpolation), tc, ts


def with_repeated_torque_value(blob: bytes) -> bytes:
    """The image with its second torque axis value set to the first (CRC made valid again): the
    encoder refuses such an axis, so the refusal of the drive is tested on bytes patched by hand."""
    body = bytearray(blob[:-4])
    first = struct.unpack_from("<f", body, lut_image.HEADER.size)[0]
    struct.pack_into("<f", body, lut_image.HEADER.size + 4, first)
    return bytes(body) + struct.pack("<I", zlib.crc32(body))


def test_download_crc_read_back_and_refusal_keeps_old_lut(drive):
    assert [read(drive, 0x2001, sub) for sub in (2, 3, 4)] == [0, 0, 0]  # no LUT yet
    good, _, _ = image(map_id=41)
    write(drive, 0x2001, 1, good)
    assert read(drive, 0x2001, 2) == zlib.crc32(good[:-4]) == lut_image.image_crc(good)
    assert read(drive, 0x2001, 3) == 1
    assert read(drive, 0x2001, 4) == 41
    for bad in (
        good[:-1] + bytes([good[-1] ^ 1]),  # CRC
        b"XCL1" + good[4:],  # magic
        good[:40],  # length
        with_repeated_torque_value(good),  # axis
        good[:4] + b"\x01\x00" + good[6:],  # format version 1
        good[:4] + b"\x04\x00" + good[6:],
    ):  # format version 4
        with pytest.raises(canopen.SdoAbortedError) as exc:
            write(drive, 0x2001, 1, bad)
        assert exc.value.code == 0x08000020
        assert read(drive, 0x2001, 2) == lut_image.image_crc(good)  # the old LUT stays in force
        assert read(drive, 0x2001, 4) == 41
        assert read(drive, 0x2001, 3) == 2
    assert drive.lut is not None and drive.lut.crc == lut_image.image_crc(good)
    other, _, _ = image(scale=2.0, map_id=42)  # another map: another CRC
    write(drive, 0x2001, 1, other)
    assert read(drive, 0x2001, 4) == 42 and read(drive, 0x2001, 2) == lut_image.image_crc(other) != lut_image.image_crc(
        good
    )


def test_lut_mode_injects_the_interpolated_theta(drive):
    blob, tc, ts = image()
    write(drive, 0x2001, 1, blob)
    write(drive, 0x2000, 2, 2)  # mode LUT
    write(drive, 0x6071, 0, 500)  # 2.5 Nm
    sp = ph.new_setpoints()
    while drive.chunk_setpoints(sp, 12.0):
        pass
    drive.speed_rpm = 2000.0  # a grid point
    drive.chunk_setpoints(sp, 12.0)
    assert (sp[ph.S_THETA_COS], sp[ph.S_THETA_SIN]) == pytest.approx((tc[0, 1, 1], ts[0, 1, 1]), abs=1e-7)
    drive.speed_rpm = 1500.0  # between points: bilinear in (torque, speed)
    drive.torque_nm = 3.25
    drive.chunk_setpoints(sp, 12.0)
    exp_c = 0.25 * (tc[0, 0, 1] + tc[0, 0, 2] + tc[0, 1, 1] + tc[0, 1, 2])
    exp_s = 0.25 * (ts[0, 0, 1] + ts[0, 0, 2] + ts[0, 1, 1] + ts[0, 1, 2])
    assert (sp[ph.S_THETA_COS], sp[ph.S_THETA_SIN]) == pytest.approx((exp_c, exp_s), abs=1e-7)
    drive.speed_rpm = 9000.0  # clamped at the axis end
    drive.torque_nm = 0.0
    drive.chunk_setpoints(sp, 30.0)
    assert (sp[ph.S_THETA_COS], sp[ph.S_THETA_SIN]) == pytest.approx((tc[0, 1, 0], ts[0, 1, 0]), abs=1e-7)
    assert sp[ph.S_H] == 6.0


def test_lut_invalid_cells_count_as_zero_and_gamma_max_clamps(drive):
    valid = np.ones((1, 2, 3), dtype=np.uint8)
    valid[0, 1, 1] = 0
    blob, tc, ts = image(scale=100.0, valid=valid, h=12)
    write(drive, 0x2001, 1, blob)
    write(drive, 0x2000, 2, 2)
    sp = ph.new_setpoints()
    while drive.chunk_setpoints(sp, 12.0):
        pass
    drive.torque_nm, drive.speed_rpm = 2.5, 2000.0
    drive.chunk_setpoints(sp, 12.0)
    assert (sp[ph.S_THETA_COS], sp[ph.S_THETA_SIN]) == (0.0, 0.0)
    assert sp[ph.S_H] == 12.0  # the LUT's order
    drive.torque_nm = 4.0
    drive.chunk_setpoints(sp, 12.0)
    assert math.hypot(sp[ph.S_THETA_COS], sp[ph.S_THETA_SIN]) == pytest.approx(drive.gamma_max_rad, rel=1e-9)


def test_voltage_estimate_switch_is_a_setpoint(drive):
    sp = ph.new_setpoints()
    write(drive, 0x2000, 8, 1)
    assert drive.chunk_setpoints(sp, 12.0) and sp[ph.S_VEST] == 1.0 and sp[ph.S_SYNC] == 1.0
    with pytest.raises(canopen.SdoAbortedError):
        write(drive, 0x2000, 8, 2)
    write(drive, 0x2000, 8, 0)
    assert drive.chunk_setpoints(sp, 12.0) and sp[ph.S_VEST] == 0.0 and sp[ph.S_SYNC] == 0.0


def _lut_mode_theta(drive, torque_nm: float, speed_rpm: float, udc_v: float = 12.0) -> tuple[float, float]:
    """The theta the control loop gets in LUT mode at an operating point (all setpoints applied first)."""
    sp = ph.new_setpoints()
    while drive.chunk_setpoints(sp, udc_v):
        pass
    drive.torque_nm, drive.speed_rpm = torque_nm, speed_rpm
    drive.chunk_setpoints(sp, udc_v)
    return float(sp[ph.S_THETA_COS]), float(sp[ph.S_THETA_SIN])


def _theta_deg(gamma_deg: float, delta_deg: float) -> tuple[float, float]:
    g, d = math.radians(gamma_deg), math.radians(delta_deg)
    return g * math.cos(d), -g * math.sin(d)


def _gamma_delta_deg(tc: float, ts: float) -> tuple[float, float]:
    return math.degrees(math.hypot(tc, ts)), math.degrees(-math.atan2(ts, tc)) % 360.0


def test_v3_polar_image_with_a_filled_cell_on_a_non_uniform_axis(drive):
    """Torque 1, 2, 4 Nm (non-uniform); speed 1000, 2000 rpm. Cells at 1000 rpm: gamma 3 deg at delta
    350, 10 (filled), 10 deg; at 2000 rpm: no entry, ok 3 deg at 90 deg, ok 3 deg at 10 deg."""
    cells = [(3.0, 350.0), (3.0, 10.0), (3.0, 10.0), (0.0, 0.0), (3.0, 90.0), (3.0, 10.0)]
    thetas = [_theta_deg(*c) for c in cells]
    flags = [1, 2, 1, 0, 1, 1]
    blob = lut_image.encode(
        6,
        [1.0, 2.0, 4.0],
        [1000.0, 2000.0],
        [12.0],
        [t[0] for t in thetas],
        [t[1] for t in thetas],
        flags,
        map_id=77,
        interpolation="polar",
    )
    write(drive, 0x2001, 1, blob)
    assert (read(drive, 0x2001, 4), read(drive, 0x2001, 3)) == (77, 1)
    assert (drive.lut.format_version, drive.lut.interpolation) == (3, "polar")
    write(drive, 0x2000, 2, 2)
    # the filled cell's own grid point: its fill
    assert _gamma_delta_deg(*_lut_mode_theta(drive, 2.0, 1000.0)) == pytest.approx((3.0, 10.0), abs=1e-5)
    # across the wrap, midway between 350 and 10 deg: 0 deg, gamma 3 deg
    g, d = _gamma_delta_deg(*_lut_mode_theta(drive, 1.5, 1000.0))
    assert g == pytest.approx(3.0, rel=1e-6) and min(d, 360.0 - d) == pytest.approx(0.0, abs=1e-5)
    # 2.5 Nm is 1/4 of 2 .. 4 Nm: weights 3/4, 1/4 on the 2000 rpm line: delta 90 -> 10 deg: 70 deg
    assert _gamma_delta_deg(*_lut_mode_theta(drive, 2.5, 2000.0)) == pytest.approx((3.0, 70.0), abs=1e-5)
    # midway (1.5 Nm) on the 2000 rpm line: the corner without an entry gives gamma 0, no phase
    assert _gamma_delta_deg(*_lut_mode_theta(drive, 1.5, 2000.0)) == pytest.approx((1.5, 90.0), abs=1e-5)
    # gamma_max clamps the polar result as any other
    write(drive, 0x2000, 5, math.radians(2.0))
    assert _gamma_delta_deg(*_lut_mode_theta(drive, 2.5, 2000.0)) == pytest.approx((2.0, 70.0), abs=1e-5)


def test_a_version_2_image_is_still_taken_and_interpolated_cartesian(drive):
    """Built here with struct as the version 2 encoder wrote it (byte 7 reserved, valid 0/1)."""
    tc, ts = [0.02, 0.04, 0.0, 0.01], [-0.01, 0.03, 0.0, -0.02]
    body = struct.pack("<4sHBBHHHHI", b"RCL1", 2, 6, 0, 2, 2, 1, 0, 12)
    body += struct.pack("<5f", 1.0, 4.0, 1000.0, 2000.0, 12.0) + struct.pack("<4f", *tc) + struct.pack("<4f", *ts)
    body += bytes([1, 1, 0, 1])
    blob = body + struct.pack("<I", zlib.crc32(body))
    write(drive, 0x2001, 1, blob)
    assert (read(drive, 0x2001, 2), read(drive, 0x2001, 4), read(drive, 0x2001, 3)) == (zlib.crc32(body), 12, 1)
    assert (drive.lut.format_version, drive.lut.interpolation) == (2, "cartesian")
    write(drive, 0x2000, 2, 2)
    # 1.75 Nm is 1/4 of 1 .. 4 Nm, 1250 rpm 1/4 of 1000 .. 2000 rpm; the invalid cell counts 0
    w = {0: 0.75 * 0.75, 1: 0.25 * 0.75, 2: 0.75 * 0.25, 3: 0.25 * 0.25}
    expected = (sum(w[k] * tc[k] for k in w), sum(w[k] * ts[k] for k in w))
    assert _lut_mode_theta(drive, 1.75, 1250.0) == pytest.approx(expected, abs=1e-8)
    # a version 2 image with a filled flag (2) does not exist: refused, the LUT in force stays
    bad = body[:-1] + b"\x02"
    with pytest.raises(canopen.SdoAbortedError):
        write(drive, 0x2001, 1, bad + struct.pack("<I", zlib.crc32(bad)))
    assert read(drive, 0x2001, 4) == 12 and read(drive, 0x2001, 3) == 2


def _polar_turning_image() -> bytes:
    """A polar LUT whose theta turns 90 deg between 1000 and 1100 rpm and 150 deg more by 1300 rpm (the
    field-weakening turn's order of steepness: 0.9 deg/rpm), at 1 and 4 Nm."""
    speeds = [800.0, 1000.0, 1100.0, 1300.0, 1600.0]
    deltas = [0.0, 10.0, 100.0, 250.0, 300.0]
    thetas = [_theta_deg(3.0 - 0.3 * it, d) for d in deltas for it in range(2)]  # cells [speed][torque]
    return lut_image.encode(
        6,
        [1.0, 4.0],
        speeds,
        [12.0],
        [t[0] for t in thetas],
        [t[1] for t in thetas],
        None,
        map_id=9,
        interpolation="polar",
    )


def test_lut_mode_schedules_theta_along_speed_for_the_control_loop(drive):
    """The loop's chunk-rate task takes theta at its own speed from the drive's schedule: linear between
    points every 1 rpm over the LUT's speed axis, it stays within 0.2 % of |theta| of Lut.theta (a chord of a
    0.9 deg arc is far less), also beyond the axis, where both hold the end's value; other modes schedule
    nothing."""
    write(drive, 0x2001, 1, _polar_turning_image())
    assert drive.theta_schedule().shape == (0, 3)  # mode off: the setpoints' theta holds
    write(drive, 0x2000, 2, 2)
    write(drive, 0x2000, 5, math.radians(10.0))  # gamma_max above the LUT's 3 deg
    _lut_mode_theta(drive, 1.75, 1000.0)
    schedule = drive.theta_schedule()
    assert schedule.shape == (801, 3)  # the LUT's speed axis, 800..1600 rpm, every rpm
    assert drive.theta_schedule() is schedule  # made once for the setpoints in force
    rng = np.random.default_rng(5)
    for speed_rpm in rng.uniform(700.0, 1700.0, 300):  # also beyond the axis ends, where the LUT clamps
        got = ph.scheduled_theta(schedule, speed_rpm * 2.0 * math.pi / 60.0)
        want = drive.lut.theta(drive.torque_nm, speed_rpm, 12.0)
        assert math.dist(got, want) <= 2e-3 * math.hypot(*want)
    _lut_mode_theta(drive, 3.0, 1000.0)
    assert drive.theta_schedule() is not schedule  # another torque command: another schedule


def test_lut_theta_follows_a_ramp_within_a_piece_as_the_drive_would():
    """Along a 200 rpm/s ramp through the turn, one 16-chunk piece (the emulator's fast mode) injects
    what 16 pieces of one chunk inject (each with its own schedule and setpoints): the LUT is looked up
    at every chunk-rate task, not once per piece. The injection angle v_inj agrees sample by sample."""
    sc = scn.load("paper-bench")
    params, tab = scn.build(sc)
    params[ph.P_NOISE] = 0.0
    traces = []
    for pieces in (1, 16):
        d = DriveFirmware(canopen.Network(), 5, str(DRIVE_EDS))
        d.state = State402.OPERATION_ENABLED
        write(d, 0x2001, 1, _polar_turning_image())
        write(d, 0x2000, 2, 2)
        write(d, 0x2000, 5, math.radians(10.0))
        write(d, 0x6071, 0, round(2000.0 / d.rated_torque_nm))  # 2 Nm
        plant = ph.Plant(params, tab, noise_seed=0, chunk=256)
        plant.init_op(2.0, 1000.0, 12.0)
        sp = ph.new_setpoints(12.0)
        sp[ph.S_LOAD_ON] = 1.0
        sp[ph.S_LOAD_SPEED] = 1300.0 * 2.0 * math.pi / 60.0
        sp[ph.S_LOAD_ACCEL] = sp[ph.S_LOAD_DECEL] = 200.0 * 2.0 * math.pi / 60.0
        parts = []
        n = 16 * 256 // pieces
        for _ in range(pieces):
            while d.chunk_setpoints(sp, 12.0):
                pass
            parts.append(
                plant.run(sp, n, trace=True, frames=False, theta_schedule=d.theta_schedule())[3][:, ph.TR_V_INJ]
            )
        traces.append(np.concatenate(parts))
    speeds_rpm = float(plant.x[ph.X_OMEGA_M]) * 60.0 / (2.0 * math.pi)
    assert speeds_rpm > 1040.0  # the piece ramped through a good part of the turn
    assert np.max(np.abs(traces[0] - traces[1])) <= 1e-3 * np.max(np.abs(traces[0]))
