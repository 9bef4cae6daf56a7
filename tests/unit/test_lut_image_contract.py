"""The LUT image contract (drivers/lut_image.py): one encoder and one decoder, imported by the service's
builder (service/maps/lut_export.py) and the emulated drive firmware; the image bytes after the header are
those the two separate implementations produced before they were merged into one codec; the CRC is
CRC-32 of the image without its CRC field, so two maps have two CRCs. Format version 3: the layout
read byte by byte, the flags (0 none, 1 ok, 2 filled), the interpolation mode, both modes against
closed forms (non-uniform axes by position, the 0/360 deg wrap, corners without an entry), and a
version 2 image still decoded."""

from __future__ import annotations

import hashlib
import math
import struct
import zlib

import numpy as np
import pytest

from drivers import lut_image
from service.maps.lut_export import lut_image as service_image

AXES = {"torque_nm": [1.0, 2.5, 4.0], "speed_rpm": [1000.0, 2000.0], "udc_v": [12.0, 24.0]}
# sha256 of the 156-byte format_version 1 image of FIXED_MAP, recorded from service/maps/lut_export.py at
# commit e535cf8 (its own struct-based builder, before the codec moved to drivers/lut_image.py)
IMAGE_SHA256_BEFORE = "13b598b43bd3a1b202d398b6f899d1a24e33ba6182beebdd231bc7e66ac8929f"
V1_HEADER = struct.Struct("<4sHBBHHHH")  # version 2 appended u32 map_id to it
RESIDUE = 0x2144DF1C  # CRC-32 over any image including its own CRC: the old bug
MAP_ID = 7


def fixed_map() -> dict:
    """12 cells, theta_cos = 0.01 k, theta_sin = -0.003 k^2 (k = 1..12 in [udc][speed][torque] order),
    every 4th cell below target (not valid)."""
    cells, k = [], 0
    for u in AXES["udc_v"]:
        for n in AXES["speed_rpm"]:
            for t in AXES["torque_nm"]:
                k += 1
                cells.append(
                    {
                        "torque_nm": t,
                        "speed_rpm": n,
                        "udc_v": u,
                        "theta_cos": 0.01 * k,
                        "theta_sin": -0.003 * k * k,
                        "status": "ok" if k % 4 else "below_target",
                    }
                )
    return {"id": MAP_ID, "harmonic_order": 6, "axes": AXES, "cells": cells}


def test_the_service_image_of_a_fixed_map_is_the_version_1_image_with_the_map_id_in_its_header():
    image = service_image(fixed_map(), interpolation="cartesian")  # mode byte 0, as version 1's reserved
    assert len(image) == 160
    magic, version, h, mode, nt, nn, nu, reserved, map_id = lut_image.HEADER.unpack_from(image)
    assert (magic, version, h, mode, nt, nn, nu, reserved, map_id) == (b"RCL1", 3, 6, 0, 3, 2, 2, 0, MAP_ID)
    # without filled cells the version 3 flags are the version 1 valid bytes (0/1), so the payload stays
    # the same payload under the version 1 header (CRC made again) is byte for byte the image of e535cf8
    v1 = V1_HEADER.pack(b"RCL1", 1, 6, 0, 3, 2, 2, 0) + image[lut_image.HEADER.size : -4]
    v1 += struct.pack("<I", zlib.crc32(v1))
    assert hashlib.sha256(v1).hexdigest() == IMAGE_SHA256_BEFORE


def test_the_crc_is_crc32_of_the_image_without_its_crc_field():
    image = service_image(fixed_map())
    crc = lut_image.image_crc(image)
    assert crc == zlib.crc32(image[:-4]) == struct.unpack("<I", image[-4:])[0]  # the trailer holds it
    assert lut_image.decode(image).crc == crc != RESIDUE
    assert zlib.crc32(image) == RESIDUE  # what the drive reported for every map before
    assert lut_image.crc_hex(crc) == f"0x{crc:08X}"


def test_two_maps_have_two_crcs():
    other_values = fixed_map()
    other_values["cells"][0]["theta_cos"] += 1e-3
    crcs = {lut_image.image_crc(service_image(m)) for m in (fixed_map(), other_values, {**fixed_map(), "id": 8})}
    assert len(crcs) == 3  # another theta, or the same values under another map id


def test_decode_refuses_another_format_version_and_map_id_0():
    image = bytearray(service_image(fixed_map()))
    struct.pack_into("<H", image, 4, 1)
    with pytest.raises(
        lut_image.LutImageError, match="unsupported format_version 1: this drive takes versions 2, 3, 4, 5, 6, 7 and 8"
    ):
        lut_image.decode(bytes(image))
    with pytest.raises(lut_image.LutImageError, match="map_id 0 is not in 1"):
        service_image({**fixed_map(), "id": 0})
    body = bytearray(service_image(fixed_map())[:-4])
    struct.pack_into("<I", body, 16, 0)
    with pytest.raises(lut_image.LutImageError, match="map_id 0 is reserved"):
        lut_image.decode(bytes(body) + struct.pack("<I", zlib.crc32(body)))


def test_decode_inverts_encode_at_float32():
    k = np.arange(1, 13, dtype=float)
    valid = (k % 4 != 0).astype(int)
    tc, ts = np.where(valid == 1, 0.01 * k, 0.0), np.where(valid == 1, -0.003 * k * k, 0.0)
    image = lut_image.encode(6, AXES["torque_nm"], AXES["speed_rpm"], AXES["udc_v"], tc, ts, valid, map_id=MAP_ID)
    assert image == service_image(fixed_map())
    lut = lut_image.decode(image)
    assert lut.harmonic_order == 6 and lut.map_id == MAP_ID and lut.crc == zlib.crc32(image[:-4])
    np.testing.assert_array_equal(lut.udc_v, AXES["udc_v"])
    np.testing.assert_array_equal(lut.valid.ravel(), valid == 1)
    np.testing.assert_array_equal(lut.theta_cos.ravel(), tc.astype(np.float32))
    np.testing.assert_array_equal(lut.theta_sin.ravel(), ts.astype(np.float32))


def test_encode_refuses_what_the_drive_would_refuse():
    with pytest.raises(lut_image.LutImageError, match="axis speed_rpm is not strictly increasing"):
        lut_image.encode(6, [1.0], [2000.0, 1000.0], [12.0], [0.0, 0.0], [0.0, 0.0], map_id=1)
    with pytest.raises(lut_image.LutImageError, match="map has 4097 cells; the drive takes at most 4096"):
        lut_image.encode(6, np.arange(4097.0), [1000.0], [12.0], np.zeros(4097), np.zeros(4097), map_id=1)
    with pytest.raises(ValueError, match="axis torque_nm is not strictly increasing"):  # the API's 422
        service_image({**fixed_map(), "axes": {**AXES, "torque_nm": [1.0, 1.0, 4.0]}})


# -- format version 3 ------------------------------------------------------------------------------


def _theta(gamma_deg: float, delta_deg: float) -> tuple[float, float]:
    """theta = [gamma cos delta, -gamma sin delta] (rad), delta = -atan2(theta_sin, theta_cos)."""
    g, d = math.radians(gamma_deg), math.radians(delta_deg)
    return g * math.cos(d), -g * math.sin(d)


def _gamma_delta_deg(tc: float, ts: float) -> tuple[float, float]:
    return math.degrees(math.hypot(tc, ts)), math.degrees(-math.atan2(ts, tc)) % 360.0


def _line(cells_deg, interpolation, flags=None, speed_rpm=(1000.0, 2000.0)):
    """A LUT over one speed line (torque and U_dc one value each): cells_deg [(gamma, delta)] per speed."""
    thetas = [_theta(*gd) for gd in cells_deg]
    return lut_image.decode(
        lut_image.encode(
            6,
            [2.5],
            list(speed_rpm),
            [12.0],
            [t[0] for t in thetas],
            [t[1] for t in thetas],
            flags,
            map_id=1,
            interpolation=interpolation,
        )
    )


def test_v3_layout_byte_by_byte():
    """Read with struct at the offsets docs/interfaces.md gives, not with the codec."""
    tc, ts = [0.01, -0.02, 0.03, 0.0], [-0.005, 0.004, 0.002, 0.0]
    image = lut_image.encode(
        12,
        [1.0, 4.0],
        [1000.0, 1800.0],
        [24.0],
        tc,
        [ts[0], ts[1], ts[2], 0.7],
        [1, 2, 1, 0],
        map_id=0x01020304,
        interpolation="polar",
    )
    cells = 4
    assert len(image) == 20 + 4 * (2 + 2 + 1) + 4 * cells + 4 * cells + cells + 4 == 80
    assert image[0:4] == b"RCL1"
    assert struct.unpack_from("<H", image, 4) == (3,)  # format_version
    assert (image[6], image[7]) == (12, 1)  # harmonic order, interpolation polar
    assert struct.unpack_from("<HHHH", image, 8) == (2, 2, 1, 0)  # n_torque, n_speed, n_udc, reserved
    assert struct.unpack_from("<I", image, 16) == (0x01020304,)  # map id
    assert struct.unpack_from("<5f", image, 20) == (1.0, 4.0, 1000.0, 1800.0, 24.0)
    assert struct.unpack_from("<4f", image, 40) == pytest.approx(tc, abs=1e-8)
    # flag 0: no entry, so theta goes in as 0 whatever was passed (0.7 here)
    assert struct.unpack_from("<4f", image, 56) == pytest.approx([ts[0], ts[1], ts[2], 0.0], abs=1e-8)
    assert list(image[72:76]) == [1, 2, 1, 0]  # flags: ok, filled, ok, none
    assert struct.unpack_from("<I", image, 76) == (zlib.crc32(image[:76]),)
    lut = lut_image.decode(image)
    assert (lut.format_version, lut.interpolation, lut.harmonic_order, lut.map_id) == (3, "polar", 12, 0x01020304)
    assert lut.flags.tolist() == [[[1, 2], [1, 0]]]
    assert lut.valid.tolist() == [[[True, False], [True, False]]] and lut.filled.tolist() == [
        [[False, True], [False, False]]
    ]


def test_cartesian_and_polar_midpoints_of_gamma_3_deg_at_delta_0_and_90():
    cells = [(3.0, 0.0), (3.0, 90.0)]
    gamma, delta = _gamma_delta_deg(*_line(cells, "cartesian").theta(2.5, 1500.0, 12.0))
    assert gamma == pytest.approx(3.0 * math.cos(math.radians(45.0)), rel=1e-6) and delta == pytest.approx(
        45.0, abs=1e-5
    )
    gamma, delta = _gamma_delta_deg(*_line(cells, "polar").theta(2.5, 1500.0, 12.0))
    assert gamma == pytest.approx(3.0, rel=1e-6) and delta == pytest.approx(45.0, abs=1e-5)


def test_polar_takes_the_shortest_arc_across_the_0_360_wrap():
    cells = [(3.0, 350.0), (3.0, 10.0)]
    gamma, delta = _gamma_delta_deg(*_line(cells, "polar").theta(2.5, 1500.0, 12.0))
    assert gamma == pytest.approx(3.0, rel=1e-6)
    assert min(delta, 360.0 - delta) == pytest.approx(0.0, abs=1e-5)  # 0 deg, not 180
    # a quarter of the way from 350 deg: 355 deg (along the arc through 360)
    _, delta = _gamma_delta_deg(*_line(cells, "polar").theta(2.5, 1250.0, 12.0))
    assert delta == pytest.approx(355.0, abs=1e-5)
    # cartesian: the chord, gamma 3 cos 10 deg at 0 deg
    gamma, delta = _gamma_delta_deg(*_line(cells, "cartesian").theta(2.5, 1500.0, 12.0))
    assert gamma == pytest.approx(3.0 * math.cos(math.radians(10.0)), rel=1e-6)
    assert min(delta, 360.0 - delta) == pytest.approx(0.0, abs=1e-5)


def test_non_uniform_axis_interpolates_by_position():
    """Speed 1000, 1200, 2000 rpm: 1400 rpm is 1/4 of the way from 1200 to 2000: weights 3/4 and 1/4."""
    speeds = (1000.0, 1200.0, 2000.0)
    cells = [(9.0, 123.0), (2.0, 40.0), (4.0, 80.0)]
    gamma, delta = _gamma_delta_deg(*_line(cells, "polar", speed_rpm=speeds).theta(2.5, 1400.0, 12.0))
    assert gamma == pytest.approx(0.75 * 2.0 + 0.25 * 4.0, rel=1e-6) and delta == pytest.approx(50.0, abs=1e-5)
    tc, ts = _line(cells, "cartesian", speed_rpm=speeds).theta(2.5, 1400.0, 12.0)
    (c1, s1), (c2, s2) = _theta(*cells[1]), _theta(*cells[2])
    assert (tc, ts) == pytest.approx((0.75 * c1 + 0.25 * c2, 0.75 * s1 + 0.25 * s2), abs=1e-8)
    # clamped at the axis ends, both modes
    for mode in ("cartesian", "polar"):
        lut = _line(cells, mode, speed_rpm=speeds)
        assert _gamma_delta_deg(*lut.theta(2.5, 5000.0, 12.0)) == pytest.approx((4.0, 80.0), abs=1e-5)
        assert _gamma_delta_deg(*lut.theta(0.0, 100.0, 99.0)) == pytest.approx((9.0, 123.0), abs=1e-5)


def test_corners_without_an_entry_give_gamma_0_and_no_phase():
    cells = [(3.0, 60.0), (3.0, 200.0)]
    flags = [1, 0]
    # polar: gamma 1/2 * 3 + 1/2 * 0; delta the entry's own (the corner without one has no phase)
    gamma, delta = _gamma_delta_deg(*_line(cells, "polar", flags).theta(2.5, 1500.0, 12.0))
    assert gamma == pytest.approx(1.5, rel=1e-6) and delta == pytest.approx(60.0, abs=1e-5)
    # cartesian: theta 0 there, so half of the entry's theta (the same point here)
    gamma, delta = _gamma_delta_deg(*_line(cells, "cartesian", flags).theta(2.5, 1500.0, 12.0))
    assert gamma == pytest.approx(1.5, rel=1e-6) and delta == pytest.approx(60.0, abs=1e-5)
    # a filled cell (flag 2) is an entry as an ok one is
    for mode in ("cartesian", "polar"):
        lut = _line(cells, mode, [1, 2])
        assert _gamma_delta_deg(*lut.theta(2.5, 2000.0, 12.0)) == pytest.approx((3.0, 200.0), abs=1e-5)
        assert lut.theta(2.5, 2000.0, 12.0) != _line(cells, mode, flags).theta(2.5, 2000.0, 12.0) == (0.0, 0.0)


def test_polar_unwraps_against_the_corner_of_largest_weight():
    """Bilinear cell, torque 1 .. 2 Nm, speed 1000 .. 2000 rpm, at (1.75 Nm, 1250 rpm): weights
    c00 = 0.25*0.75, c10 = 0.75*0.75 (the largest), c01 = 0.25*0.25, c11 = 0.75*0.25. Deltas: c10 240,
    c00 0, c11 120, c01 no entry. Unwrapped against 240: 0 -> 360, 120 -> 120, so
    delta = (0.5625*240 + 0.1875*360 + 0.1875*120) / 0.9375 = 240 deg; gamma = 3 * 0.9375 deg.
    (Against c00's 0 deg it would be -48 deg.)"""
    deltas = {(0, 0): 0.0, (0, 1): 240.0, (1, 0): 999.0, (1, 1): 120.0}  # [speed][torque]
    tc = [[_theta(3.0, deltas[(j, i)])[0] for i in range(2)] for j in range(2)]
    ts = [[_theta(3.0, deltas[(j, i)])[1] for i in range(2)] for j in range(2)]
    image = lut_image.encode(
        6, [1.0, 2.0], [1000.0, 2000.0], [12.0], [tc], [ts], [[[1, 1], [0, 2]]], map_id=1, interpolation="polar"
    )
    gamma, delta = _gamma_delta_deg(*lut_image.decode(image).theta(1.75, 1250.0, 12.0))
    assert gamma == pytest.approx(3.0 * 0.9375, rel=1e-6) and delta == pytest.approx(240.0, abs=1e-5)


def test_a_version_2_image_still_decodes_as_valid_cells_and_cartesian_interpolation():
    """Built here with struct, as the version 2 encoder wrote it: byte 7 reserved, valid 0/1."""
    tc, ts, valid = [0.02, 0.04], [-0.01, 0.03], [1, 0]
    body = struct.pack("<4sHBBHHHHI", b"RCL1", 2, 6, 0, 1, 2, 1, 0, 9)
    body += struct.pack("<4f", 2.5, 1000.0, 3000.0, 12.0) + struct.pack("<2f", *tc) + struct.pack("<2f", *ts)
    body += bytes(valid)
    image = body + struct.pack("<I", zlib.crc32(body))
    lut = lut_image.decode(image)
    assert (lut.format_version, lut.interpolation, lut.map_id, lut.crc) == (2, "cartesian", 9, zlib.crc32(body))
    assert lut.flags.tolist() == [[[1], [0]]]
    # at 1500 rpm (1/4 of the way): 3/4 of the valid cell's theta, the invalid one counts 0
    assert lut.theta(2.5, 1500.0, 12.0) == pytest.approx((0.75 * 0.02, 0.75 * -0.01), abs=1e-8)
    # a version 2 image knows no filled flag
    bad = bytearray(body)
    bad[-1] = 2
    with pytest.raises(lut_image.LutImageError, match="flags must be one of"):
        lut_image.decode(bytes(bad) + struct.pack("<I", zlib.crc32(bytes(bad))))


def test_decode_refuses_a_bad_flag_interpolation_or_reserved_field():
    good = lut_image.encode(6, [1.0], [1000.0, 2000.0], [12.0], [0.01, 0.02], [0.0, 0.0], [1, 2], map_id=3)

    def patched(offset: int, value: int) -> bytes:
        body = bytearray(good[:-4])
        body[offset] = value
        return bytes(body) + struct.pack("<I", zlib.crc32(bytes(body)))

    with pytest.raises(lut_image.LutImageError, match="flags must be one of"):
        lut_image.decode(patched(len(good) - 5, 3))
    with pytest.raises(lut_image.LutImageError, match="interpolation 3 unknown"):
        lut_image.decode(patched(7, 3))
    with pytest.raises(lut_image.LutImageError, match="reserved header field"):
        lut_image.decode(patched(14, 1))
    with pytest.raises(lut_image.LutImageError, match="flags must be 0"):
        lut_image.encode(6, [1.0], [1000.0], [12.0], [0.0], [0.0], [4], map_id=1)
    with pytest.raises(lut_image.LutImageError, match="interpolation 'spline' is not one of cartesian, polar, cubic"):
        lut_image.encode(6, [1.0], [1000.0], [12.0], [0.0], [0.0], map_id=1, interpolation="spline")


def test_the_service_image_takes_the_filled_cells_only_with_fill_and_names_the_mode():
    m = fixed_map()
    filled = m["cells"][3]  # k = 4: below target; a fill of 0.05 / -0.01 rad
    filled.update(filled=True, fill_source="interpolated (cartesian) from ok cells", theta_cos=0.05, theta_sin=-0.01)
    with_fill = lut_image.decode(service_image(m, fill=True, interpolation="cartesian"))
    without = lut_image.decode(service_image(m, fill=False))
    assert (with_fill.interpolation, without.interpolation) == ("cartesian", lut_image.DEFAULT_INTERPOLATION)
    # cell k = 4 is [udc 0][speed 1][torque 0]; k = 8 and 12 stay holes (below target, no fill)
    assert with_fill.flags[0, 1, 0] == 2 and without.flags[0, 1, 0] == 0
    assert (with_fill.theta_cos[0, 1, 0], with_fill.theta_sin[0, 1, 0]) == pytest.approx((0.05, -0.01), abs=1e-8)
    assert (without.theta_cos[0, 1, 0], without.theta_sin[0, 1, 0]) == (0.0, 0.0)
    assert int((with_fill.flags == 1).sum()) == int((without.flags == 1).sum()) == 9
    assert int((with_fill.flags == 0).sum()) == 2 and int((without.flags == 0).sum()) == 3
    assert lut_image.DEFAULT_INTERPOLATION == "polar"
