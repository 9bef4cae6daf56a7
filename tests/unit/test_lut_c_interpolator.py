"""The exported C header's reference interpolator (`ripplecal_lut_map<ID>_theta`, service/maps/lut_export.py
export_c) gives the drive's theta: compiled by gcc (-std=c99 -Wall -Wextra -Werror, at -O0 and -O2) and
compared with the interpolation the emulated drive runs (drivers.lut_image.decode(lut_image(m)).theta, then
the clamp to gamma_max of plant_emulator/drive_firmware.py effective_theta) at every grid point, every
midpoint, points beyond the axis ends, seeded random points and non-finite ones, cartesian, polar and cubic, with
and without the fill, on maps with filled cells, holes, injection-off cells, a zero theta, non-uniform and
one-value axes, phases that wrap around +-180 deg and phases that turn once around a cell (the
reference corner's tie-break decides).

The quantum: no theta object of the drive is an integer (0x2000:3/:4/:5 and the LUT image are REAL32), so
the agreement asked for is one step of an int16 spanning +-gamma_max at its default (0x2000:5 in
drivers/eds/drive.eds, 0.2617994 rad = 15 deg): 0.2617994 / 32767 = 8.0e-6 rad. The C function runs in
float32, the drive's emulator in float64 on the same float32 table and the same float32 point; measured
at most 4.0e-8 rad."""

from __future__ import annotations

import configparser
import itertools
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest

from drivers import lut_image
from service.maps.lut_export import cell_count, export_map, image_bytes
from service.maps.lut_export import lut_image as service_image
from service.maps.view import MapCell
from tests.support.c_lut import HeaderTheta, build, f32, needs_gcc
from tests.support.maps import map_dict

EDS = Path(__file__).resolve().parents[2] / "drivers" / "eds" / "drive.eds"


def default_gamma_max_rad() -> float:
    eds = configparser.ConfigParser()
    eds.read(EDS)
    return float(eds["2000sub5"]["DefaultValue"])


THETA_QUANTUM_RAD = default_gamma_max_rad() / 32767

Point = tuple[float, float, float]


def make_map(map_id: int, axes: dict[str, list[float]], gamma_delta_deg, kinds: dict[Point, str]) -> dict:
    """A map as GET /maps/{id} gives it: theta from gamma_delta_deg(point) -> (gamma, delta) in deg; kinds
    names the cells that are "filled" (a fill, not ok), "hole" (failed, no theta) or "off" (ok, injection off)."""
    cells = []
    for u, n, t in itertools.product(axes["udc_v"], axes["speed_rpm"], axes["torque_nm"]):
        p = (t, n, u)
        kind = kinds.get(p, "ok")
        if kind == "hole":
            cells.append(MapCell(torque_nm=t, speed_rpm=n, udc_v=u, status="failed", error="boom"))
            continue
        g, d = gamma_delta_deg(p)
        tc, ts = math.radians(g) * math.cos(math.radians(d)), -math.radians(g) * math.sin(math.radians(d))
        filled = kind == "filled"
        cells.append(
            MapCell(
                torque_nm=t,
                speed_rpm=n,
                udc_v=u,
                status="below_target" if filled else "ok",
                result_id=1,
                gamma_deg=g,
                delta_deg=d % 360.0,
                theta_cos=tc,
                theta_sin=ts,
                suppression_db=30.0,
                filled=filled,
                fill_source="interpolated" if filled else None,
                injection_off=kind == "off",
            )
        )
    counts = {"ok": sum(c.status == "ok" for c in cells), "failed": sum(c.status == "failed" for c in cells)}
    return map_dict(map_id, axes, cells, counts)


def turning(p: Point) -> tuple[float, float]:
    """gamma 0.5 .. 6 deg, delta turning by tens of degrees across the map (as at the field-weakening turn)."""
    t, n, u = p
    return 0.5 + 0.8 * t + 1e-3 * n - 0.02 * u, 30.0 + 40.0 * math.sin(n / 700.0) * t / 4.0 - 0.5 * u


def wrapping(p: Point) -> tuple[float, float]:
    """delta 150 .. 215 deg: crosses +-180 deg (delta = -atan2 jumps there), gamma 2 .. 4 deg."""
    t, n, _u = p
    return 2.0 + 0.5 * t, 150.0 + 0.04 * (n - 1000.0) + 5.0 * t


NON_UNIFORM = {
    "torque_nm": [0.5, 1.0, 2.5, 4.0],
    "speed_rpm": [500.0, 1500.0, 1800.0, 2000.0, 2600.0],
    "udc_v": [12.0, 24.0, 48.0],
}


def with_integer_cells(map_id: int, cells: str) -> dict:
    """The non-uniform turning map (one ok cell at theta 0, a fill, a hole, injection off) built for integer cells."""
    return {
        **make_map(
            map_id,
            NON_UNIFORM,
            lambda p: (0.0, 0.0) if p == (2.5, 1500.0, 48.0) else turning(p),
            {(1.0, 1800.0, 12.0): "filled", (0.5, 2600.0, 24.0): "hole", (2.5, 1500.0, 24.0): "off"},
        ),
        "provenance": {"lut_cells": cells},
    }


MAPS = {
    # filled cells, holes, injection-off cells (one interior, one at a corner of the grid), a zero theta
    "non-uniform": make_map(
        41,
        NON_UNIFORM,
        lambda p: (0.0, 0.0) if p == (2.5, 1500.0, 48.0) else turning(p),
        {
            (1.0, 1800.0, 12.0): "filled",
            (2.5, 2000.0, 24.0): "filled",
            (4.0, 500.0, 48.0): "filled",
            (0.5, 2600.0, 24.0): "hole",
            (2.5, 1800.0, 48.0): "hole",
            (2.5, 1500.0, 24.0): "off",
            (4.0, 2600.0, 12.0): "off",
        },
    ),
    # one-value torque and U_dc axes: interpolation along speed only
    "one-value axes": make_map(
        42,
        {"torque_nm": [2.0], "speed_rpm": [1000.0, 1700.0, 2000.0, 3000.0], "udc_v": [24.0]},
        turning,
        {(2.0, 1700.0, 24.0): "filled", (2.0, 3000.0, 24.0): "hole"},
    ),
    "wrapping phase": make_map(
        43,
        {"torque_nm": [1.0, 2.0, 3.0], "speed_rpm": [1000.0, 1500.0, 2000.0, 2500.0], "udc_v": [12.0, 24.0]},
        wrapping,
        {(2.0, 2000.0, 12.0): "filled", (3.0, 1000.0, 24.0): "hole"},
    ),
    # the same map with int16 cells (LUT image version 5): the header carries the image's integers and quantum
    "int16 cells": with_integer_cells(45, "int16"),
    # and with int11 cells (version 6: two 11-bit integers and the flag packed in 3 bytes a cell)
    "int11 cells": with_integer_cells(46, "int11"),
    # and as a version 7 image (int11-sparse: per-row speed breakpoints, cells the drive derives along their row)
    "int11-sparse cells": with_integer_cells(47, "int11-sparse"),
    # delta turning once around the cell (0, 100, 200, 290 deg): at its centre the four corners tie and the
    # reference (the first of them) decides the result; no two corners 180 deg apart (no arc is ambiguous)
    "phase vortex": make_map(
        44,
        {"torque_nm": [1.0, 2.0], "speed_rpm": [1000.0, 2000.0], "udc_v": [12.0]},
        lambda p: (3.0, {(1.0, 1000.0): 0.0, (2.0, 1000.0): 100.0, (2.0, 2000.0): 200.0, (1.0, 2000.0): 290.0}[p[:2]]),
        {},
    ),
}


def axis_probes(axis: list[float]) -> list[float]:
    """Every breakpoint, every midpoint, and a point beyond each end."""
    span = max(axis[-1] - axis[0], 1.0)
    mids = [(a + b) / 2 for a, b in zip(axis, axis[1:])]
    return sorted([*axis, *mids, axis[0] - 0.3 * span, axis[-1] + 0.3 * span])


def probe_points(axes: dict[str, list[float]], n_random: int = 1500, seed: int = 27) -> list[Point]:
    grid = list(itertools.product(*(axis_probes(axes[k]) for k in ("torque_nm", "speed_rpm", "udc_v"))))
    rng = np.random.default_rng(seed)
    lows, highs = zip(*((a[0] - 0.1 * (a[-1] - a[0]) - 1.0, a[-1] + 0.1 * (a[-1] - a[0]) + 1.0) for a in axes.values()))
    randoms = [tuple(float(x) for x in row) for row in rng.uniform(lows, highs, size=(n_random, 3))]
    # not finite: the first breakpoint, as the drive takes it
    t0, n0, u0 = (axes[k][-1] for k in ("torque_nm", "speed_rpm", "udc_v"))
    odd = [(math.nan, n0, u0), (t0, math.inf, u0), (t0, n0, -math.inf)]
    return [(f32(t), f32(n), f32(u)) for t, n, u in grid + randoms + odd]


def drive_theta(lut: lut_image.Lut, p: Point, gamma_max_rad: float) -> tuple[float, float]:
    """What the emulated drive applies: Lut.theta, then |theta| clamped to gamma_max (effective_theta)."""
    c, s = lut.theta(*p)
    g = math.hypot(c, s)
    if g > gamma_max_rad and g > 0.0:
        return c * gamma_max_rad / g, s * gamma_max_rad / g
    return c, s


def largest_difference(name: str, interpolation: str, c_theta: HeaderTheta, points, with_fill, gamma_max_rad):
    """Largest |C - drive| over both components; exact zeros (injection off, no entry) must agree exactly."""
    lut = lut_image.decode(service_image(MAPS[name], fill=with_fill, interpolation=interpolation))
    assert lut.interpolation == interpolation
    got = c_theta.theta(points, with_fill=with_fill, gamma_max_rad=gamma_max_rad)
    worst = 0.0
    for p, c in zip(points, got, strict=True):
        drive = drive_theta(lut, p, gamma_max_rad)
        assert (c == (0.0, 0.0)) == (drive == (0.0, 0.0)), (name, interpolation, with_fill, p, c, drive)
        worst = max(worst, abs(c[0] - drive[0]), abs(c[1] - drive[1]))
    return worst


@needs_gcc
@pytest.mark.parametrize("optimise", ["-O0", "-O2"])
@pytest.mark.parametrize("interpolation", lut_image.INTERPOLATIONS)
@pytest.mark.parametrize("name", list(MAPS))
def test_the_headers_theta_is_the_drives_within_one_int16_quantum(tmp_path, name, interpolation, optimise):
    m = MAPS[name]
    if interpolation == "cubic" and name == "int11-sparse cells":
        # a version 7 image derives cells from two stored ones: cubic (slopes from the neighbours) is refused
        with pytest.raises(lut_image.LutImageError, match="cubic"):
            service_image(m, interpolation=interpolation)
        return
    c_theta = HeaderTheta(tmp_path, export_map(m, "c", interpolation=interpolation), m["id"], (optimise,))
    points = probe_points(m["axes"])
    for with_fill in (True, False):
        worst = largest_difference(name, interpolation, c_theta, points, with_fill, math.inf)
        assert worst <= THETA_QUANTUM_RAD, (name, interpolation, with_fill, worst)
    # clamped as the drive clamps: below the map's gamma, and 0 (theta 0)
    for gamma_max_rad in (math.radians(2.0), 0.0):
        worst = largest_difference(name, interpolation, c_theta, points, True, gamma_max_rad)
        assert worst <= THETA_QUANTUM_RAD, (name, interpolation, gamma_max_rad, worst)


def test_the_maps_hold_what_the_docstring_says():
    m = MAPS["non-uniform"]
    lut = lut_image.decode(service_image(m, interpolation="polar"))
    assert (int(lut.filled.sum()), int((lut.flags == 0).sum()), int(lut.injection_off.sum())) == (3, 2, 2)
    assert lut.theta(2.5, 1500.0, 48.0) == (0.0, 0.0) and lut.valid[2, 1, 2]  # an ok cell with a zero theta
    # the probes hit the off cells' intervals and points where the off corner weighs 0
    points = probe_points(m["axes"])
    zeros = sum(lut.theta(*p) == (0.0, 0.0) for p in points)
    assert 0 < zeros < len(points) // 2
    # the wrapping map's delta crosses +-180 deg between neighbouring cells
    w = lut_image.decode(service_image(MAPS["wrapping phase"], interpolation="polar"))
    delta = -np.arctan2(w.theta_sin, w.theta_cos)
    assert delta.max() > math.radians(170.0) and delta.min() < -math.radians(170.0)


@needs_gcc
def test_headers_go_twice_into_one_unit_and_into_two_units_of_one_program(tmp_path):
    """Include guards and static inline functions: a header included twice, in two translation units, and
    the headers of two maps in one unit compile and link."""
    a, b = MAPS["non-uniform"], MAPS["wrapping phase"]
    unit = '#include "lut_a.h"\n#include "lut_b.h"\n#include "lut_a.h"\n'
    other = unit + (
        "float other_theta(float t)\n{\n    float c, s;\n"
        f"    ripplecal_lut_map{b['id']}_theta(t, 1500.0f, 12.0f, 1, HUGE_VALF, &c, &s);\n    return c;\n}}\n"
    )
    main = unit + (
        "#include <stdio.h>\nfloat other_theta(float t);\nint main(void)\n{\n    float c, s;\n"
        f"    ripplecal_lut_map{a['id']}_theta(1.0f, 1500.0f, 12.0f, 0, 0.1f, &c, &s);\n"
        '    printf("%.9g %.9g %.9g\\n", c, s, other_theta(2.0f));\n    return 0;\n}\n'
    )
    sources = {
        "lut_a.h": export_map(a, "c", interpolation="cartesian"),
        "lut_b.h": export_map(b, "c", interpolation="polar"),
        "main.c": main,
        "other.c": other,
    }
    program = build(tmp_path, sources, ("-O2", "-pedantic"))
    c, s, other = (
        float(x) for x in subprocess.run([str(program)], capture_output=True, text=True, check=True).stdout.split()
    )
    lut_a = lut_image.decode(service_image(a, fill=False, interpolation="cartesian"))
    lut_b = lut_image.decode(service_image(b, interpolation="polar"))
    assert (c, s) == pytest.approx(drive_theta(lut_a, (1.0, 1500.0, 12.0), f32(0.1)), abs=THETA_QUANTUM_RAD)
    assert other == pytest.approx(lut_b.theta(2.0, 1500.0, 12.0)[0], abs=THETA_QUANTUM_RAD)


@pytest.mark.parametrize(
    ("cells", "version", "full_scale"),
    [("int16", lut_image.FORMAT_VERSION_INT16, 32767), ("int11", lut_image.FORMAT_VERSION_INT11, 1023)],
)
def test_an_integer_cell_map_is_its_versions_image_within_half_a_quantum_of_its_theta(cells, version, full_scale):
    """int16: version 5, 5 bytes a cell; int11: version 6, 3 bytes a cell (flag packed with theta). Both within half a
    quantum (the largest |component| / full scale) of the float image's theta, with the same flags."""
    m = MAPS[f"{cells} cells"]
    image = service_image(m, interpolation="polar")
    assert len(image) == image_bytes(m["axes"], cells) and image[4] == version
    assert image_bytes(m["axes"], cells) - image_bytes(m["axes"], "float32") == (
        4 + (lut_image.CELL_BYTES[cells] - 9) * cell_count(m["axes"])
    )
    lut = lut_image.decode(image)
    quantum = lut_image.theta_quantum(
        np.array([c["theta_cos"] or 0.0 for c in m["cells"]]),
        np.array([c["theta_sin"] or 0.0 for c in m["cells"]]),
        cells,
    )
    # the quantum: the largest |component| over the full scale (6 deg of gamma: 3.2e-6 rad in int16, 1e-4 in int11)
    assert quantum == pytest.approx(max(abs(c["theta_cos"] or 0.0) for c in m["cells"]) / full_scale, rel=1e-6)
    float_lut = lut_image.decode(service_image({**m, "provenance": None}, interpolation="polar"))
    assert np.max(np.abs(lut.theta_cos - float_lut.theta_cos)) <= quantum / 2 + 1e-9
    assert np.max(np.abs(lut.theta_sin - float_lut.theta_sin)) <= quantum / 2 + 1e-9
    assert np.array_equal(lut.flags, float_lut.flags) and int(lut.injection_off.sum()) == 1
