"""Injection off (issue 27, "never worse than nothing"): LUT flag 3 in a format_version 4 image makes the
drive inject exactly nothing in any interval that has an off cell as a corner of non-zero weight, in both
interpolations (drivers/lut_image.py); an image without off cells stays the version 3 image it was, byte
for byte; a map cell's `injection_off` (Storage.set_injection_off) goes into the image and every export,
and the exported C header's own interpolator honours it as the drive's decoder does.

The map: torque 1, 2, 3 Nm x speed 1000, 2000 rpm at 12 V; gamma linear in the operating point at a
constant delta (so cartesian and polar both reproduce it exactly between entries); the cell (1 Nm,
1000 rpm) off. The interval 1..2 Nm touches it, the interval 2..3 Nm does not."""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import struct
import zlib

import numpy as np
import pytest

from drivers import lut_image
from service.maps.lut_export import export_map, lut_entries
from service.maps.lut_export import lut_image as service_image
from service.maps.view import map_view
from tests.support.c_lut import HeaderTheta, needs_gcc
from tests.support.maps import make_map, theta_of

TORQUE_NM, SPEED_RPM, UDC_V = [1.0, 2.0, 3.0], [1000.0, 2000.0], [12.0]
OFF = (1.0, 1000.0, 12.0)
DELTA_DEG = 40.0
MAP_ID = 9
# sha256, CRC and length of the image below encoded by drivers/lut_image.py before format_version 4
# (commit 6104de0): a map without off cells must stay that image byte for byte
V3_SHA256 = "769bc24e39d2df7e71e62547f2eae62fcf9b462a2ce75f9b849b43bae5db8694"
V3_CRC, V3_BYTES = 0x7A3F8F89, 102


def gamma_deg(t: float, n: float) -> float:
    return 1.0 + 0.5 * t + 1e-3 * n


def theta(t: float, n: float, u: float = 12.0) -> tuple[float, float]:
    return theta_of(gamma_deg(t, n), DELTA_DEG)


def grid(flag_at) -> tuple[list, list, list]:
    """[udc][speed][torque] arrays of theta_cos, theta_sin and the flag (flag_at(point) per cell)."""
    tc = [[[theta(t, n)[0] for t in TORQUE_NM] for n in SPEED_RPM]]
    ts = [[[theta(t, n)[1] for t in TORQUE_NM] for n in SPEED_RPM]]
    flags = [[[flag_at((t, n, 12.0)) for t in TORQUE_NM] for n in SPEED_RPM]]
    return tc, ts, flags


def image(interpolation: str, off: bool = True) -> bytes:
    tc, ts, flags = grid(lambda p: lut_image.FLAG_OFF if off and p == OFF else lut_image.FLAG_OK)
    return lut_image.encode(6, TORQUE_NM, SPEED_RPM, UDC_V, tc, ts, flags, map_id=MAP_ID, interpolation=interpolation)


# -- the codec ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("interpolation", lut_image.INTERPOLATIONS)
def test_an_off_corner_gives_exactly_zero_in_its_interval_and_its_neighbour_interpolates(interpolation):
    lut = lut_image.decode(image(interpolation))
    assert (lut.format_version, lut.interpolation, int(lut.injection_off.sum())) == (4, interpolation, 1)
    # every point of the interval 1..2 Nm x 1000..2000 rpm where (1 Nm, 1000 rpm) weighs > 0: exactly 0,
    # its edges and the off grid point included; clamped below the axis it is the off cell again
    for t, n in [(1.5, 1500.0), (1.0, 1000.0), (1.999, 1999.0), (1.0, 1999.0), (1.5, 1000.0), (0.5, 900.0)]:
        assert lut.theta(t, n, 12.0) == (0.0, 0.0), (t, n)
    # the neighbouring interval 2..3 Nm does not touch it: gamma linear at a constant delta, exact
    for t, n in [(2.5, 1500.0), (2.25, 1000.0), (3.0, 2000.0)]:
        assert lut.theta(t, n, 12.0) == pytest.approx(theta(t, n), abs=1e-8), (t, n)
    # on the shared edge (2 Nm) and along the far speed line (2000 rpm) the off corner weighs 0
    assert lut.theta(2.0, 1500.0, 12.0) == pytest.approx(theta(2.0, 1500.0), abs=1e-8)
    assert lut.theta(1.5, 2000.0, 12.0) == pytest.approx(theta(1.5, 2000.0), abs=1e-8)
    # the same image without the off flag interpolates the interval as usual
    plain = lut_image.decode(image(interpolation, off=False))
    assert plain.theta(1.5, 1500.0, 12.0) == pytest.approx(theta(1.5, 1500.0), abs=1e-8)


def test_a_version_4_image_round_trips_and_keeps_the_off_cells_theta_for_the_record():
    blob = image("polar")
    magic, version, _h, mode, nt, nn, nu, reserved, map_id = lut_image.HEADER.unpack_from(blob)
    assert (magic, version, mode, nt, nn, nu, reserved, map_id) == (b"RCL1", 4, 1, 3, 2, 1, 0, MAP_ID)
    assert len(blob) == 24 + 4 * 6 + 9 * 6  # the version 3 layout
    lut = lut_image.decode(blob)
    assert lut.flags.tolist() == [[[3, 1, 1], [1, 1, 1]]]
    assert (lut.theta_cos[0, 0, 0], lut.theta_sin[0, 0, 0]) == pytest.approx(theta(1.0, 1000.0), abs=1e-8)
    assert not lut.entry[0, 0, 0] and not lut.valid[0, 0, 0] and lut.entry.sum() == 5
    assert lut.crc == lut_image.image_crc(blob) == struct.unpack("<I", blob[-4:])[0]
    # encode(decode(x)) == x
    again = lut_image.encode(
        lut.harmonic_order,
        lut.torque_nm,
        lut.speed_rpm,
        lut.udc_v,
        lut.theta_cos,
        lut.theta_sin,
        lut.flags,
        map_id=lut.map_id,
        interpolation=lut.interpolation,
    )
    assert again == blob


def test_without_off_cells_encode_writes_the_version_3_image_of_before_byte_for_byte():
    tc = [[[0.01, 0.02, 0.03], [0.015, 0.025, 0.035]]]
    ts = [[[-0.01, -0.02, -0.03], [-0.005, -0.015, -0.025]]]
    blob = lut_image.encode(
        6, TORQUE_NM, SPEED_RPM, UDC_V, tc, ts, [[[1, 2, 0], [1, 1, 2]]], map_id=9, interpolation="polar"
    )
    assert (hashlib.sha256(blob).hexdigest(), lut_image.image_crc(blob), len(blob)) == (V3_SHA256, V3_CRC, V3_BYTES)
    lut = lut_image.decode(blob)
    assert lut.format_version == 3 and not lut.injection_off.any()


def test_flag_3_is_refused_in_a_version_3_image_and_version_4_is_what_the_drive_takes():
    blob = bytearray(image("cartesian")[:-4])
    struct.pack_into("<H", blob, 4, 3)  # the same flags under a version 3 header
    with pytest.raises(lut_image.LutImageError, match="flags must be one of .* in a format_version 3 image"):
        lut_image.decode(bytes(blob) + struct.pack("<I", zlib.crc32(bytes(blob))))
    struct.pack_into("<H", blob, 4, 9)
    with pytest.raises(lut_image.LutImageError, match="takes versions 2, 3, 4, 5, 6, 7 and 8"):
        lut_image.decode(bytes(blob) + struct.pack("<I", zlib.crc32(bytes(blob))))


# -- a stored map: the flag, its image, its exports ---------------------------------------------------


def off_map(storage) -> dict:
    grid_axes = {"torque_nm": TORQUE_NM, "speed_rpm": SPEED_RPM, "udc_v": UDC_V}
    map_id = make_map(storage, grid_axes, lambda p: theta(p[0], p[1]))
    assert storage.set_injection_off(map_id, [OFF]) == 1
    view = map_view(storage, map_id)
    assert view is not None
    return view.model_dump()


def test_storage_sets_and_clears_injection_off_all_or_nothing(storage):
    grid_axes = {"torque_nm": TORQUE_NM, "speed_rpm": SPEED_RPM, "udc_v": UDC_V}
    map_id = make_map(storage, grid_axes, lambda p: theta(p[0], p[1]))
    before = map_view(storage, map_id)
    assert before is not None and before.injection_off_cells == 0
    assert not any(c.injection_off for c in before.cells)
    assert storage.set_injection_off(map_id, [OFF, (2.0, 2000.0, 12.0)]) == 2
    assert storage.set_injection_off(map_id, [OFF]) == 0  # already off
    view = map_view(storage, map_id)
    assert view is not None and view.injection_off_cells == 2
    off = {(c.torque_nm, c.speed_rpm, c.udc_v) for c in view.cells if c.injection_off}
    assert off == {OFF, (2.0, 2000.0, 12.0)}
    # the off cell keeps its result and theta for the record
    cell = next(c for c in view.cells if (c.torque_nm, c.speed_rpm, c.udc_v) == OFF)
    assert cell.status == "ok" and (cell.theta_cos, cell.theta_sin) == pytest.approx(theta(1.0, 1000.0), abs=1e-12)
    with pytest.raises(ValueError, match="has no cell at 9 Nm / 1000 rpm / 12 V"):
        storage.set_injection_off(map_id, [(2.0, 2000.0, 12.0), (9.0, 1000.0, 12.0)], off=False)
    assert map_view(storage, map_id).injection_off_cells == 2  # nothing changed
    assert storage.set_injection_off(map_id, [(2.0, 2000.0, 12.0)], off=False) == 1
    assert map_view(storage, map_id).injection_off_cells == 1


def test_the_maps_image_carries_the_off_cell_as_flag_3_and_it_is_no_hole(storage):
    m = off_map(storage)
    entries = lut_entries(m)
    assert (entries.cells, entries.ok, entries.injection_off, entries.holes, entries.format_version) == (6, 5, 1, 0, 4)
    lut = lut_image.decode(service_image(m, interpolation="cartesian"))
    assert lut.format_version == 4 and lut.flags.tolist() == [[[3, 1, 1], [1, 1, 1]]]
    assert lut.theta(1.5, 1500.0, 12.0) == (0.0, 0.0)
    assert lut.theta(2.5, 1500.0, 12.0) == pytest.approx(theta(2.5, 1500.0), abs=1e-8)
    # cleared again: the version 3 image of the same map
    m["cells"][0]["injection_off"] = False
    assert lut_image.decode(service_image(m)).format_version == 3


def test_every_export_carries_the_off_cell(storage, tmp_path):
    m = off_map(storage)
    text = export_map(m, "csv")
    assert "1 cell(s) with injection off" in text and "LUT image format_version 4" in text
    rows = list(csv.DictReader(io.StringIO("\n".join(line for line in text.splitlines() if not line.startswith("#")))))
    by = {(float(r["torque_nm"]), float(r["speed_rpm"]), float(r["udc_v"])): r for r in rows}
    assert [p for p, r in by.items() if r["injection_off"] == "1"] == [OFF]
    assert by[OFF]["filled"] == "0" and by[OFF]["status"] == "ok"
    assert float(by[OFF]["theta_cos_rad"]) == pytest.approx(theta(1.0, 1000.0)[0], abs=1e-15)  # the record

    doc = json.loads(export_map(m, "json"))
    assert (doc["format_version"], doc["lut_format_version"]) == (4, 4)
    assert doc["injection_off"] == [[[1, 0, 0], [0, 0, 0]]] and doc["valid"] == [[[0, 1, 1], [1, 1, 1]]]
    assert [(c["torque_nm"], c["speed_rpm"], c["udc_v"]) for c in doc["cells"] if c["injection_off"]] == [OFF]

    dcm = export_map(m, "dcm")
    block = dcm[dcm.index("KENNFELD RIPPLECAL_H6_INJECTION_OFF_U12V") :].split("END")[0]
    assert [line.split()[1:] for line in block.splitlines() if "WERT" in line] == [["1", "0", "0"], ["0", "0", "0"]]

    header = export_map(m, "c")
    assert f"#define RIPPLECAL_LUT_MAP{m['id']}_INJECTION_OFF_CELLS 1u" in header
    assert f"ripplecal_lut_map{m['id']}_injection_off[1][2][3] = {{{{{{1u, 0u, 0u}}, {{0u, 0u, 0u}}}}}};" in header


POINTS = [(1.5, 1500.0), (1.0, 1999.0), (2.0, 1500.0), (2.5, 1500.0), (1.5, 2000.0), (2.9, 1100.0)]


@needs_gcc
def test_the_exported_headers_own_interpolator_agrees_with_the_drives_decoder(storage, tmp_path):
    m = off_map(storage)
    c_theta = HeaderTheta(tmp_path, export_map(m, "c", interpolation="cartesian"), m["id"])
    lut = lut_image.decode(service_image(m, interpolation="cartesian"))
    points = [(t, n, 12.0) for t, n in POINTS]
    for p, c in zip(points, c_theta.theta(points), strict=True):
        drive = lut.theta(*p)
        if drive == (0.0, 0.0):
            assert c == (0.0, 0.0), p
        else:
            assert c == pytest.approx(drive, abs=1e-7), p
    assert sum(1 for p in points if lut.theta(*p) == (0.0, 0.0)) == 2  # both ways tested


def test_gamma_is_linear_and_delta_constant_as_the_docstring_says():
    for t in TORQUE_NM:
        for n in SPEED_RPM:
            tc, ts = theta(t, n)
            assert math.degrees(math.hypot(tc, ts)) == pytest.approx(gamma_deg(t, n), abs=1e-12)
            assert math.degrees(-math.atan2(ts, tc)) == pytest.approx(DELTA_DEG, abs=1e-9)
    assert np.isclose(gamma_deg(1.5, 1500.0), (gamma_deg(1.0, 1000.0) + gamma_deg(2.0, 2000.0)) / 2)
