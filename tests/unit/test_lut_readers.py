"""Every export of a refined map (non-uniform axes) with filled cells, read back by its real reader:
the C header compiled by gcc with a small C main that calls the header's own interpolator, the DCM by dcmReader,
CSV and JSON by the standard library, the LUT image by the drive's own decoder (drivers.lut_image,
which the emulated firmware uses). Expected values are closed forms of the map below, never the
exporters' own output.

The map: torque 1, 2, 4 Nm; speed 1000, 1500, 1800, 2000, 2600 rpm (a refined speed axis); U_dc 12,
24 V. theta linear in the operating point (so multilinear interpolation reproduces it exactly); two
cells below target carry a fill (FILLED, theta = the linear value), one failed cell has no entry."""

from __future__ import annotations

import csv
import io
import json
import math
import subprocess

import pytest

from drivers import lut_image
from service.maps.lut_export import export_map
from service.maps.lut_export import lut_image as service_image
from service.maps.view import MapCell
from tests.support.c_lut import HeaderTheta, build, needs_gcc
from tests.support.dcm_read import read_dcm
from tests.support.maps import map_dict

AXES = {"torque_nm": [1.0, 2.0, 4.0], "speed_rpm": [1000.0, 1500.0, 1800.0, 2000.0, 2600.0], "udc_v": [12.0, 24.0]}
MAP_ID = 31
FILLED = {
    (2.0, 1800.0, 12.0): "interpolated (cartesian) from ok cells: speed_rpm between 1500 and 2000",
    (1.0, 1000.0, 24.0): "measured: its own theta (no_authority, 12.0 dB against the uncompensated harmonic)",
}
HOLE = (4.0, 2600.0, 24.0)


def theta(t: float, n: float, u: float) -> tuple[float, float]:
    """theta (rad), linear in torque (Nm), speed (rpm) and U_dc (V)."""
    return (0.01 + 0.004 * t - 5e-6 * n + 5e-4 * u, -0.03 + 0.002 * t + 1e-5 * n - 4e-4 * u)


def gamma_delta_deg(tc: float, ts: float) -> tuple[float, float]:
    """gamma = |theta|, delta = -atan2(theta_sin, theta_cos) in [0, 360) deg."""
    return math.degrees(math.hypot(tc, ts)), math.degrees(-math.atan2(ts, tc)) % 360.0


def refined_map() -> dict:
    """The map as GET /maps/{id} gives it (MapView.model_dump(): GET /maps/{id} adds its validation)."""
    cells = []
    for u in AXES["udc_v"]:
        for n in AXES["speed_rpm"]:
            for t in AXES["torque_nm"]:
                p = (t, n, u)
                if p == HOLE:
                    cells.append(MapCell(torque_nm=t, speed_rpm=n, udc_v=u, status="failed", error="boom"))
                    continue
                tc, ts = theta(*p)
                g, d = gamma_delta_deg(tc, ts)
                if p in FILLED:
                    cells.append(
                        MapCell(
                            torque_nm=t,
                            speed_rpm=n,
                            udc_v=u,
                            status="below_target",
                            result_id=7,
                            gamma_deg=g,
                            delta_deg=d,
                            theta_cos=tc,
                            theta_sin=ts,
                            suppression_db=31.0,
                            filled=True,
                            fill_source=FILLED[p],
                        )
                    )
                else:
                    cells.append(
                        MapCell(
                            torque_nm=t,
                            speed_rpm=n,
                            udc_v=u,
                            status="ok",
                            result_id=1,
                            gamma_deg=g,
                            delta_deg=d,
                            theta_cos=tc,
                            theta_sin=ts,
                            suppression_db=45.0,
                            quality="consistent",
                        )
                    )
    counts = {"ok": 27, "below_target": 2, "failed": 1}
    return map_dict(MAP_ID, AXES, cells, counts)


def test_the_map_is_what_the_docstring_says():
    m = refined_map()
    assert len(m["cells"]) == 3 * 5 * 2 and sum(c["status"] == "ok" for c in m["cells"]) == 27
    assert sum(c["filled"] for c in m["cells"]) == 2


# -- C header: gcc --------------------------------------------------------------------------------

C_MAIN = r"""
#include <stdio.h>
#include "lut.h"
#define M(x) RIPPLECAL_LUT_MAP31_##x
#define A(x) ripplecal_lut_map31_##x

int main(void)
{
    printf("%u %u %u %u %u %d %d\n", M(ID), M(N_TORQUE), M(N_SPEED), M(N_UDC), M(FILLED_CELLS),
           M(INTERPOLATION) == M(INTERPOLATION_CARTESIAN), M(INTERPOLATION) == M(INTERPOLATION_POLAR));
    printf("%u %u %u %u\n", A(valid)[0][2][1], A(filled)[0][2][1], A(valid)[1][4][2], A(filled)[1][4][2]);
    printf("%.9g %.9g %.9g %.9g\n", A(speed_rpm)[1], A(speed_rpm)[2], A(speed_rpm)[3], A(torque_nm)[2]);
    printf("%.9g %.9g\n", A(theta_cos_rad)[1][0][0], A(theta_sin_rad)[1][4][2]);
    return 0;
}
"""


@needs_gcc
def test_c_header_compiles_and_its_own_function_interpolates_it_by_position(tmp_path):
    header = export_map(refined_map(), "c", interpolation="cartesian")
    program = build(tmp_path, {"lut.h": header, "main.c": C_MAIN})
    lines = subprocess.run([str(program)], capture_output=True, text=True, check=True).stdout.splitlines()
    assert lines[0].split() == [str(MAP_ID), "3", "5", "2", "2", "1", "0"]  # cartesian, 2 filled cells
    assert lines[1].split() == ["0", "1", "0", "0"]  # the filled cell; the hole
    assert [float(x) for x in lines[2].split()] == [1500.0, 1800.0, 2000.0, 4.0]
    # the fill at (1 Nm, 1000 rpm, 24 V) is in the theta array; the hole's theta is 0
    assert float(lines[3].split()[0]) == pytest.approx(theta(1.0, 1000.0, 24.0)[0], abs=1e-8)
    assert float(lines[3].split()[1]) == 0.0
    (tmp_path / "theta").mkdir()
    c_theta = HeaderTheta(tmp_path / "theta", header, MAP_ID)
    ((tc, ts),) = c_theta.theta([(2.5, 1575.0, 12.0)], with_fill=True)
    ((tc0, ts0),) = c_theta.theta([(2.5, 1575.0, 12.0)], with_fill=False)
    # 2.5 Nm is 1/4 of 2 .. 4 Nm, 1575 rpm 1/4 of 1500 .. 1800 rpm: theta is linear, so exact
    assert (tc, ts) == pytest.approx(theta(2.5, 1575.0, 12.0), abs=2e-7)
    # without the fill the corner (2 Nm, 1800 rpm) counts 0: weight 3/4 (torque) x 1/4 (speed)
    f_tc, f_ts = theta(2.0, 1800.0, 12.0)
    assert (tc0, ts0) == pytest.approx((tc - 3 / 16 * f_tc, ts - 3 / 16 * f_ts), abs=2e-7)


# -- DCM: dcmReader -------------------------------------------------------------------------------


def test_dcm_reads_in_dcmreader_with_the_refined_axis_points_valid_and_filled(tmp_path, caplog):
    maps = read_dcm(tmp_path, export_map(refined_map(), "dcm"), caplog)
    assert set(maps) == {
        f"RIPPLECAL_H6_{kind}_U{u}V"
        for kind in ("THETA_COS", "THETA_SIN", "VALID", "FILLED", "INJECTION_OFF")
        for u in (12, 24)
    }
    for name, k in maps.items():
        u = 12.0 if name.endswith("_U12V") else 24.0
        # values[speed][torque]: each KENNFELD its own axis points, the refined ones as they are
        assert (k.x_dimension, k.y_dimension, k.unit_x, k.unit_y) == (3, 5, "Nm", "rpm")
        assert [float(n) for n in k.values] == AXES["speed_rpm"]
        for n, row in k.values.items():
            assert [float(t) for t in row] == AXES["torque_nm"]
            for t, value in row.items():
                p = (float(t), float(n), u)
                if "_VALID_" in name:
                    assert value == (0 if p in FILLED or p == HOLE else 1), (name, p)
                elif "_FILLED_" in name:
                    assert value == (1 if p in FILLED else 0), (name, p)
                elif "_INJECTION_OFF_" in name:
                    assert value == 0, (name, p)
                else:
                    expected = 0.0 if p == HOLE else theta(*p)[0 if "_COS_" in name else 1]
                    assert value == pytest.approx(expected, abs=1e-10), (name, p)  # 9 digits


# -- CSV and JSON ---------------------------------------------------------------------------------


def test_csv_has_filled_and_fill_source_columns():
    text = export_map(refined_map(), "csv")
    comments = [line for line in text.splitlines() if line.startswith("#")]
    assert any(f"LUT interpolation: {lut_image.DEFAULT_INTERPOLATION}" in line for line in comments)
    assert any("2 filled cell(s)" in line for line in comments)
    rows = list(csv.DictReader(io.StringIO("\n".join(line for line in text.splitlines() if not line.startswith("#")))))
    assert len(rows) == 30
    by = {(float(r["torque_nm"]), float(r["speed_rpm"]), float(r["udc_v"])): r for r in rows}
    for p, source in FILLED.items():
        r = by[p]
        assert (r["status"], r["filled"], r["fill_source"]) == ("below_target", "1", source)
        assert (float(r["theta_cos_rad"]), float(r["theta_sin_rad"])) == pytest.approx(theta(*p), abs=1e-15)
        assert (float(r["gamma_deg"]), float(r["delta_deg"])) == pytest.approx(gamma_delta_deg(*theta(*p)), abs=1e-9)
    hole = by[HOLE]
    assert (hole["filled"], hole["fill_source"], float(hole["theta_cos_rad"]), hole["gamma_deg"]) == ("0", "", 0.0, "")
    assert all(r["filled"] == "0" for p, r in by.items() if p not in FILLED)


def test_json_carries_filled_apart_from_valid_and_the_interpolation_mode():
    doc = json.loads(export_map(refined_map(), "json", interpolation="polar"))
    assert (doc["format_version"], doc["interpolation"], doc["lut_format_version"]) == (4, "polar", 3)
    assert sum(v for plane in doc["injection_off"] for row in plane for v in row) == 0
    assert json.loads(export_map(refined_map(), "json"))["interpolation"] == lut_image.DEFAULT_INTERPOLATION
    assert doc["axes"] == AXES and doc["index_order"] == ["udc_v", "speed_rpm", "torque_nm"]
    # [udc][speed][torque]: (2 Nm, 1800 rpm, 12 V) is [0][2][1]; (1 Nm, 1000 rpm, 24 V) [1][0][0]; the hole [1][4][2]
    assert (doc["valid"][0][2][1], doc["filled"][0][2][1]) == (0, 1)
    assert (doc["valid"][1][0][0], doc["filled"][1][0][0]) == (0, 1)
    assert (doc["valid"][1][4][2], doc["filled"][1][4][2], doc["theta_cos_rad"][1][4][2]) == (0, 0, 0.0)
    assert sum(v for plane in doc["valid"] for row in plane for v in row) == 27
    assert doc["theta_cos_rad"][0][2][1] == pytest.approx(theta(2.0, 1800.0, 12.0)[0], abs=1e-15)
    filled = {(c["torque_nm"], c["speed_rpm"], c["udc_v"]): c["fill_source"] for c in doc["cells"] if c["filled"]}
    assert filled == FILLED


# -- the drive's own decoder ------------------------------------------------------------------------


def test_image_round_trip_both_modes_with_and_without_fill():
    m = refined_map()
    for mode in lut_image.INTERPOLATIONS:
        with_fill = lut_image.decode(service_image(m, fill=True, interpolation=mode))
        without = lut_image.decode(service_image(m, fill=False, interpolation=mode))
        assert (with_fill.format_version, with_fill.interpolation) == (3, mode)
        assert with_fill.speed_rpm.tolist() == AXES["speed_rpm"] and with_fill.torque_nm.tolist() == AXES["torque_nm"]
        assert (with_fill.flags[0, 2, 1], with_fill.flags[1, 0, 0], with_fill.flags[1, 4, 2]) == (2, 2, 0)
        assert (without.flags[0, 2, 1], without.flags[1, 0, 0], without.flags[1, 4, 2]) == (0, 0, 0)
        assert int(with_fill.valid.sum()) == int(without.valid.sum()) == 27
        # every grid point of an entry: its own theta (float32)
        for p in [(2.0, 1800.0, 12.0), (4.0, 2000.0, 24.0), (1.0, 2600.0, 12.0)]:
            assert with_fill.theta(*p) == pytest.approx(theta(*p), abs=1e-8)
        assert with_fill.theta(*HOLE) == (0.0, 0.0) and without.theta(2.0, 1800.0, 12.0) == (0.0, 0.0)

    # cartesian between grid points: exact for a linear theta (1/4 of 2 .. 4 Nm, 1/4 of 1500 .. 1800 rpm,
    # 1/3 of 12 .. 24 V)
    cart = lut_image.decode(service_image(m, interpolation="cartesian"))
    assert cart.theta(2.5, 1575.0, 16.0) == pytest.approx(theta(2.5, 1575.0, 16.0), abs=1e-8)
    cart0 = lut_image.decode(service_image(m, fill=False, interpolation="cartesian"))
    f = theta(2.0, 1800.0, 12.0)
    assert cart0.theta(2.5, 1575.0, 12.0) == pytest.approx(
        tuple(a - 3 / 16 * b for a, b in zip(theta(2.5, 1575.0, 12.0), f)), abs=1e-8
    )

    # polar on the 2 Nm line at 1575 rpm: 3/4 of (2 Nm, 1500 rpm) and 1/4 of the filled (2 Nm, 1800 rpm)
    (ga, da), (gb, db) = gamma_delta_deg(*theta(2.0, 1500.0, 12.0)), gamma_delta_deg(*theta(2.0, 1800.0, 12.0))
    db_unwrapped = da + (db - da + 180.0) % 360.0 - 180.0
    polar = lut_image.decode(service_image(m, interpolation="polar"))
    g, d = gamma_delta_deg(*polar.theta(2.0, 1575.0, 12.0))
    assert g == pytest.approx(0.75 * ga + 0.25 * gb, rel=1e-6)
    assert d == pytest.approx((0.75 * da + 0.25 * db_unwrapped) % 360.0, abs=1e-5)
    # without the fill: gamma 3/4 of the ok corner's, the phase its own
    polar0 = lut_image.decode(service_image(m, fill=False, interpolation="polar"))
    g, d = gamma_delta_deg(*polar0.theta(2.0, 1575.0, 12.0))
    assert g == pytest.approx(0.75 * ga, rel=1e-6) and d == pytest.approx(da, abs=1e-5)


def test_a_map_placed_in_cartesian_interpolation_is_imaged_and_exported_so_unless_another_is_named():
    """A refinement records the interpolation it placed and validated the map in (provenance): the LUT image's
    header, the C header's mode and the JSON, DCM and CDFX exports say it without being asked, as its validation
    judged it; a mode named still wins; a map without one keeps the drive's default."""
    plain = refined_map()
    placed = {**plain, "provenance": {**(plain.get("provenance") or {}), "interpolation": "cartesian"}}
    assert lut_image.DEFAULT_INTERPOLATION == "polar"  # (else this case proves nothing)
    assert lut_image.decode(service_image(placed)).interpolation == "cartesian"
    assert lut_image.decode(service_image(placed, interpolation="polar")).interpolation == "polar"
    assert lut_image.decode(service_image(plain)).interpolation == "polar"
    assert json.loads(export_map(placed, "json"))["interpolation"] == "cartesian"
    assert json.loads(export_map(plain, "json"))["interpolation"] == "polar"
    macro = f"RIPPLECAL_LUT_MAP{MAP_ID}"
    assert f"#define {macro}_INTERPOLATION {macro}_INTERPOLATION_CARTESIAN" in export_map(placed, "c")
    assert f"#define {macro}_INTERPOLATION {macro}_INTERPOLATION_POLAR" in export_map(placed, "c", "polar")
    for fmt in ("dcm", "cdfx"):
        assert export_map(placed, fmt) == export_map(plain, fmt, "cartesian")
