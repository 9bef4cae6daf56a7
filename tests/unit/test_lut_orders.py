"""A map of several orders (issue 28) through every reader: the LUT image of several orders (format version 8)
decoded by the drive's own decoder and injected by the emulated drive firmware in LUT mode (every order at once,
one scale on their sum), the C header's own functions compiled by gcc, the DCM by dcmReader, CSV and JSON by the
standard library. Expected values are closed forms of the map below, never the exporters' own output.

The map: torque 1, 2, 4 Nm; speed 1000, 1500, 2600 rpm; U_dc 12 V; orders 6 (the map's own) and 12. Each order's
theta is linear in the operating point (multilinear interpolation reproduces it exactly) with its own
coefficients; one cell of the 12th is below target and carries a fill, one of the 6th has failed (no entry)."""

from __future__ import annotations

import csv
import io
import json
import math
import struct
import zlib

import canopen
import numpy as np
import pytest

from drivers import DRIVE_EDS, lut_image
from drivers.cia402 import State402
from plant_emulator import physics as ph
from plant_emulator.drive_firmware import INJ_LUT, DriveFirmware
from service.maps.lut_export import export_map
from service.maps.lut_export import lut_image as service_image
from service.maps.view import MapCell, OrderMap, order_map
from tests.support.c_lut import build, f32, needs_gcc
from tests.support.dcm_read import read_dcm
from tests.support.maps import map_dict

AXES = {"torque_nm": [1.0, 2.0, 4.0], "speed_rpm": [1000.0, 1500.0, 2600.0], "udc_v": [12.0]}
MAP_ID = 52
HOLE_6 = (4.0, 2600.0, 12.0)  # failed: no entry in the 6th
FILLED_12 = (2.0, 1500.0, 12.0)  # below target in the 12th: carries a fill (the linear value)


def theta(order: int, t: float, n: float, u: float) -> tuple[float, float]:
    """theta (rad) of each order, linear in torque (Nm) and speed (rpm), each order its own."""
    if order == 6:
        return (0.01 + 0.004 * t - 5e-6 * n, -0.03 + 0.002 * t + 1e-5 * n)
    return (-0.004 + 0.001 * t + 2e-6 * n, 0.006 - 0.0015 * t + 1e-6 * n)


def _cells(order: int) -> list[MapCell]:
    cells = []
    for u in AXES["udc_v"]:
        for n in AXES["speed_rpm"]:
            for t in AXES["torque_nm"]:
                p = (t, n, u)
                if order == 6 and p == HOLE_6:
                    cells.append(MapCell(torque_nm=t, speed_rpm=n, udc_v=u, status="failed", error="boom"))
                    continue
                tc, ts = theta(order, *p)
                filled = order == 12 and p == FILLED_12
                cells.append(
                    MapCell(
                        torque_nm=t,
                        speed_rpm=n,
                        udc_v=u,
                        status="below_target" if filled else "ok",
                        theta_cos=tc,
                        theta_sin=ts,
                        suppression_db=30.0 if filled else 45.0,
                        filled=filled,
                        fill_source="measured: its own theta" if filled else None,
                    )
                )
    return cells


def two_order_map() -> dict:
    """The map as GET /maps/{id} gives it (MapView.model_dump())."""
    further = OrderMap(order=12, status_counts={"ok": 8, "below_target": 1}, filled_cells=1, cells=_cells(12))
    return map_dict(
        MAP_ID,
        AXES,
        _cells(6),
        {"ok": 8, "failed": 1},
        method="probe-orders",
        orders=[6, 12],
        further_orders=[further],
    )


POINTS = [(1.0, 1000.0, 12.0), (1.5, 1250.0, 12.0), (3.0, 2000.0, 12.0), (2.0, 1500.0, 12.0), (0.5, 3000.0, 12.0)]


def _clamped(t: float, n: float) -> tuple[float, float]:
    """The point clamped to the axes' ends (the drive holds the end values beyond them)."""
    return min(max(t, 1.0), 4.0), min(max(n, 1000.0), 2600.0)


def test_the_image_carries_every_order_and_each_interpolates_its_own():
    m = two_order_map()
    blob = service_image(m, interpolation="cartesian")
    lut = lut_image.decode(blob)
    assert lut.format_version == lut_image.FORMAT_VERSION_ORDERS and lut.orders == (6, 12)
    assert lut.map_id == MAP_ID and lut.crc == zlib.crc32(blob[:-4])
    assert struct.unpack_from("<4sHBBI", blob, 0) == (b"RCL1", 8, 2, 0, MAP_ID)
    twelfth = lut.further[0]
    for t, n, u in POINTS:
        tc, ts = _clamped(t, n)
        if (tc, ts) == (4.0, 2600.0):
            continue
        # cartesian: multilinear of a linear theta is the theta itself (away from the 6th's hole)
        if not (tc > 2.0 and ts > 1500.0):
            assert lut.theta(t, n, u) == pytest.approx(theta(6, tc, ts, u), abs=1e-6)
        assert twelfth.theta(t, n, u) == pytest.approx(theta(12, tc, ts, u), abs=1e-6)
    # the 12th's fill goes in as flag 2, the 6th's failed cell as no entry
    assert twelfth.flags[0, 1, 1] == lut_image.FLAG_FILLED and lut.flags[0, 2, 2] == lut_image.FLAG_NONE
    # each order's image is the one a map of that order alone gives
    assert struct.unpack_from("<I", blob, 12)[0] == len(service_image(order_map(m, 6), interpolation="cartesian"))


def test_a_map_of_one_order_keeps_its_image_byte_for_byte():
    m = two_order_map()
    one = {**m, "orders": [6], "further_orders": []}
    assert service_image(one) == service_image(order_map(m, 6))
    assert lut_image.decode(service_image(one)).further == ()


def _container(parts: list[bytes], n_orders: int | None = None, map_id: int = MAP_ID) -> bytes:
    body = struct.pack("<4sHBBI", b"RCL1", 8, len(parts) if n_orders is None else n_orders, 0, map_id)
    for part in parts:
        body += struct.pack("<I", len(part)) + part
    return body + struct.pack("<I", zlib.crc32(body))


def test_a_bad_image_of_several_orders_is_refused_with_what_is_wrong():
    m = two_order_map()
    six, twelve = (service_image(order_map(m, h)) for h in (6, 12))
    assert lut_image.decode(_container([six, twelve])).orders == (6, 12)
    cases = {
        "order 2's image": _container([six, twelve[:-1] + bytes([twelve[-1] ^ 1])]),  # the 12th's own CRC
        "name an order twice": _container([six, six]),
        "not in 2 .. 4": _container([six]),
        "ends before order 3 of 3": _container([six, twelve], n_orders=3),
        "header's map id": _container([six, twelve], map_id=MAP_ID + 1),
        "CRC-32 mismatch": _container([six, twelve])[:-1] + b"\x00",
    }
    for expected, blob in cases.items():
        with pytest.raises(lut_image.LutImageError, match=expected):
            lut_image.decode(blob)
    with pytest.raises(lut_image.LutImageError, match="map ids"):
        lut_image.encode_orders([six, lut_image.encode(12, [1.0], [1000.0], [12.0], [0.0], [0.0], map_id=9)])


@pytest.fixture()
def drive():
    d = DriveFirmware(canopen.Network(), 5, str(DRIVE_EDS))
    d.state = State402.OPERATION_ENABLED
    return d


def test_the_drive_injects_every_order_of_the_lut_scaled_by_one_factor(drive):
    m = two_order_map()
    blob = service_image(m, interpolation="cartesian")
    od = drive.node.object_dictionary
    drive.node.set_data(0x2001, 1, blob, check_writable=True)
    assert od[0x2001][4].decode_raw(drive.node.get_data(0x2001, 4)) == MAP_ID
    drive.inj_mode, drive.torque_nm, drive.speed_rpm, drive.udc_v = INJ_LUT, 1.5, 1250.0, 12.0
    sp = np.zeros(ph.N_SETPOINTS)
    t6, t12 = theta(6, 1.5, 1250.0, 12.0), theta(12, 1.5, 1250.0, 12.0)
    drive.gamma_max_rad = 1.0  # above the sum: every order as the LUT gives it
    drive.chunk_setpoints(sp, 12.0)
    assert (sp[ph.S_THETA_COS], sp[ph.S_THETA_SIN]) == pytest.approx(t6, abs=1e-6)
    assert (sp[ph.S_XH_ORDER], sp[ph.S_XH_COS], sp[ph.S_XH_SIN]) == pytest.approx((12.0, *t12), abs=1e-6)
    # gamma_max below the sum of |theta|: both scaled by gamma_max / sum, the sum then exactly gamma_max
    total = math.hypot(*t6) + math.hypot(*t12)
    drive.gamma_max_rad = 0.5 * total
    drive.chunk_setpoints(sp, 12.0)
    assert (sp[ph.S_THETA_COS], sp[ph.S_THETA_SIN]) == pytest.approx((0.5 * t6[0], 0.5 * t6[1]), abs=1e-6)
    assert (sp[ph.S_XH_COS], sp[ph.S_XH_SIN]) == pytest.approx((0.5 * t12[0], 0.5 * t12[1]), abs=1e-6)
    # injection off: no order at all
    drive.inj_mode = 0
    drive.chunk_setpoints(sp, 12.0)
    assert sp[ph.S_THETA_COS] == sp[ph.S_XH_COS] == sp[ph.S_XH_ORDER] == 0.0


ORDERS_MAIN = r"""
#include <stdio.h>
#include "lut.h"

int main(void)
{
    float torque_nm, speed_rpm, udc_v, gamma_max_rad, c[2], s[2];
    while (scanf("%f %f %f %f", &torque_nm, &speed_rpm, &udc_v, &gamma_max_rad) == 4) {
        ripplecal_lut_map52_theta_orders(torque_nm, speed_rpm, udc_v, 1, gamma_max_rad, c, s);
        printf("%.9g %.9g %.9g %.9g %u %u\n", c[0], s[0], c[1], s[1], ripplecal_lut_map52_orders[0],
               ripplecal_lut_map52_orders[1]);
    }
    return 0;
}
"""


@needs_gcc
def test_c_header_of_two_orders_compiles_and_gives_the_drives_thetas(tmp_path):
    import subprocess

    m = two_order_map()
    header = export_map(m, "c", interpolation="cartesian")
    program = build(tmp_path, {"lut.h": header, "main.c": ORDERS_MAIN})
    lut = lut_image.decode(service_image(m, interpolation="cartesian"))
    points = [(1.5, 1250.0, 12.0), (3.0, 1200.0, 12.0), (1.0, 2600.0, 12.0)]
    gamma_max = 0.02
    queries = "".join(f"{f32(t):.9g} {f32(n):.9g} {f32(u):.9g} {gamma_max:.9g}\n" for t, n, u in points)
    out = subprocess.run([str(program)], input=queries, capture_output=True, text=True, check=True).stdout
    for (t, n, u), line in zip(points, out.splitlines()):
        c6, s6, c12, s12, h0, h1 = line.split()
        assert (int(h0), int(h1)) == (6, 12)
        main, further = lut.theta(t, n, u), lut.further[0].theta(t, n, u)
        total = math.hypot(*main) + math.hypot(*further)
        k = min(1.0, gamma_max / total)
        assert [float(v) for v in (c6, s6, c12, s12)] == pytest.approx(
            [k * main[0], k * main[1], k * further[0], k * further[1]], abs=2e-6
        )


def test_dcm_of_two_orders_reads_in_dcmreader_each_order_its_own(tmp_path, caplog):
    maps = read_dcm(tmp_path, export_map(two_order_map(), "dcm"), caplog)
    assert set(maps) == {
        f"RIPPLECAL_H{h}_{kind}_U12V"
        for h in (6, 12)
        for kind in ("THETA_COS", "THETA_SIN", "VALID", "FILLED", "INJECTION_OFF")
    }
    for h in (6, 12):
        for n, row in maps[f"RIPPLECAL_H{h}_THETA_SIN_U12V"].values.items():
            for t, value in row.items():
                p = (float(t), float(n), 12.0)
                expected = 0.0 if (h == 6 and p == HOLE_6) else theta(h, *p)[1]
                assert value == pytest.approx(expected, abs=1e-10), (h, p)
    filled = maps["RIPPLECAL_H12_FILLED_U12V"].values
    assert filled[1500.0][2.0] == 1 and sum(v for row in filled.values() for v in row.values()) == 1


def test_csv_and_json_of_two_orders_carry_each_order():
    m = two_order_map()
    text = export_map(m, "csv")
    assert any("several orders: 6, 12" in line for line in text.splitlines() if line.startswith("#"))
    rows = list(csv.DictReader(io.StringIO("\n".join(line for line in text.splitlines() if not line.startswith("#")))))
    assert len(rows) == 18 and {r["harmonic_order"] for r in rows} == {"6", "12"}
    for r in rows:
        h, p = int(r["harmonic_order"]), (float(r["torque_nm"]), float(r["speed_rpm"]), float(r["udc_v"]))
        expected = (0.0, 0.0) if (h == 6 and p == HOLE_6) else theta(h, *p)
        assert (float(r["theta_cos_rad"]), float(r["theta_sin_rad"])) == pytest.approx(expected, abs=1e-15)
        assert r["filled"] == ("1" if (h == 12 and p == FILLED_12) else "0")
    doc = json.loads(export_map(m, "json"))
    assert doc["orders"] == [6, 12] and [o["harmonic_order"] for o in doc["further_orders"]] == [12]
    grid = doc["further_orders"][0]["theta_cos_rad"]  # [udc][speed][torque]
    for j, n in enumerate(AXES["speed_rpm"]):
        for i, t in enumerate(AXES["torque_nm"]):
            assert grid[0][j][i] == pytest.approx(theta(12, t, n, 12.0)[0], abs=1e-15)
    assert doc["further_orders"][0]["filled"][0][1][1] == 1


def test_the_drives_limit_scales_every_order_by_one_factor_to_a_sum_of_gamma_max():
    from drivers.injection_limit import injection_scale

    # |theta_6| = 0.02, |theta_12| = 0.01 rad against gamma_max 0.02: the peak sum_k gamma_k = 0.03 -> 0.02
    assert injection_scale([0.02, 0.01], 0.02) == pytest.approx(2.0 / 3.0, rel=1e-12)
    assert injection_scale([0.015, 0.005], 0.02) == 1.0  # at the limit: untouched
    assert injection_scale([0.0, 0.0], 0.02) == 1.0
    assert injection_scale([0.05], 0.02) == pytest.approx(0.4, rel=1e-12)  # one order: |theta| <= gamma_max
