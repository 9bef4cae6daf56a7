"""The version 7 LUT image (cell_format "int11-sparse"): per-row speed breakpoints on one shared axis.

Checked against closed forms, not against the encoder's own output: the drive's theta along a row between two
stored cells is the straight interpolation of those two (cartesian: linear in theta; polar: gamma linear and
delta linear on the shorter arc), computed here by hand; which cells the encoder leaves out follows from the
suppression 20 log10 |theta| / |error| that the test works out for a row with one known bump.
"""

from __future__ import annotations

import cmath
import math
import struct
import zlib

import numpy as np
import pytest

from drivers import lut_image
from service.maps.lut_export import image_bytes, row_stored
from service.maps.lut_export import lut_image as service_image

TORQUE = [1.0, 2.0]
SPEED = [1000.0, 1100.0, 1200.0, 1300.0, 1400.0]
UDC = [12.0]
SHAPE = (1, len(SPEED), len(TORQUE))
# a version 7 image derives cells from two stored ones: cubic (slopes from the neighbours) is refused there
SPARSE_INTERPOLATIONS = [mode for mode in lut_image.INTERPOLATIONS if mode != "cubic"]


def polar(gamma_deg: float, delta_deg: float) -> complex:
    """theta from gamma and delta (theta_cos = gamma cos delta, theta_sin = -gamma sin delta), rad."""
    g, d = math.radians(gamma_deg), math.radians(delta_deg)
    return complex(g * math.cos(d), -g * math.sin(d))


def arrays(thetas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return thetas.real.copy(), thetas.imag.copy()


def random_thetas(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(0.01, 0.05, SHAPE) * np.exp(1j * rng.uniform(-math.pi, math.pi, SHAPE))


@pytest.mark.parametrize("interpolation", lut_image.INTERPOLATIONS)
def test_between_is_the_drives_interpolation_of_two_breakpoints(interpolation):
    rng = np.random.default_rng(7)
    for _ in range(300):
        a, b = (complex(*rng.normal(0.0, 0.03, 2)) for _ in range(2))
        if rng.uniform() < 0.1:
            a = 0j  # a zero theta has no phase
        x_a, x_b = sorted(rng.uniform(500.0, 3000.0, 2))
        x = float(rng.uniform(x_a - 100.0, x_b + 100.0))
        shape = (1, 2, 1)
        one_row = lut_image.Lut(
            1,
            6,
            np.array([0.0]),
            np.array([x_a, x_b]),
            np.array([0.0]),
            np.array([a.real, b.real]).reshape(shape),
            np.array([a.imag, b.imag]).reshape(shape),
            np.full(shape, lut_image.FLAG_OK, dtype=np.uint8),
            0,
            interpolation,
        )
        assert abs(lut_image.between(a, b, x_a, x_b, x, interpolation) - complex(*one_row.theta(0.0, x, 0.0))) < 1e-15


def hand_interpolation(a: complex, b: complex, f: float, interpolation: str) -> complex:
    """The closed form: cartesian (1-f) a + f b; polar gamma linear, delta linear along the shorter arc."""
    if interpolation == "cartesian":
        return (1.0 - f) * a + f * b
    delta_a, delta_b = -cmath.phase(a), -cmath.phase(b)
    arc = (delta_b - delta_a + math.pi) % (2.0 * math.pi) - math.pi
    gamma = (1.0 - f) * abs(a) + f * abs(b)
    delta = delta_a + f * arc
    return complex(gamma * math.cos(delta), -gamma * math.sin(delta))


@pytest.mark.parametrize("interpolation", SPARSE_INTERPOLATIONS)
def test_a_row_interpolates_between_its_stored_cells_only(interpolation):
    thetas = random_thetas(3)
    stored = np.ones(SHAPE, dtype=bool)
    stored[0, 1:4, 0] = False  # torque row 1 Nm: 1000 and 1400 rpm only; the 2 Nm row keeps every speed
    stored[0, 2, 1] = False
    blob = lut_image.encode(
        6, TORQUE, SPEED, UDC, *arrays(thetas), map_id=5, interpolation=interpolation, cell_format="int11-sparse"
    )
    full = lut_image.decode(
        lut_image.encode(
            6, TORQUE, SPEED, UDC, *arrays(thetas), map_id=5, interpolation=interpolation, cell_format="int11"
        )
    )
    sparse_blob = lut_image.encode(
        6,
        TORQUE,
        SPEED,
        UDC,
        *arrays(thetas),
        map_id=5,
        interpolation=interpolation,
        cell_format="int11-sparse",
        stored=stored,
    )
    sparse = lut_image.decode(sparse_blob)
    assert lut_image.decode(blob).stored.all() and sparse.format_version == lut_image.FORMAT_VERSION_SPARSE
    # every cell stored: the same cells as version 6
    np.testing.assert_array_equal(lut_image.decode(blob).theta_cos, full.theta_cos)
    # bytes: header, axes, quantum, one bit a cell, 3 bytes a stored cell, CRC
    n = len(TORQUE) * len(SPEED)
    expected = lut_image.HEADER.size + 4 * (len(TORQUE) + len(SPEED) + 1) + 4 + (n + 7) // 8 + 3 * 6 + 4
    assert len(sparse_blob) == expected
    ends = [complex(full.theta_cos[0, j, 0], full.theta_sin[0, j, 0]) for j in (0, 4)]
    for speed in np.linspace(1000.0, 1400.0, 41):
        f = (speed - 1000.0) / 400.0
        got = complex(*sparse.theta(1.0, float(speed), 12.0))
        assert abs(got - hand_interpolation(ends[0], ends[1], f, interpolation)) < 1e-12
    # the 2 Nm row: 1100 -> 1300 straight, the stored cells as they are
    a, b = (complex(full.theta_cos[0, j, 1], full.theta_sin[0, j, 1]) for j in (1, 3))
    assert abs(complex(*sparse.theta(2.0, 1250.0, 12.0)) - hand_interpolation(a, b, 0.75, interpolation)) < 1e-12
    assert abs(complex(*sparse.theta(2.0, 1100.0, 12.0)) - a) < 1e-15
    assert sparse.flags[0, 2, 1] == lut_image.FLAG_OK and not sparse.stored[0, 2, 1]


def test_malformed_sparse_images_are_refused_with_what_is_wrong():
    thetas = random_thetas(4)
    stored = np.ones(SHAPE, dtype=bool)
    stored[0, -1, 0] = False
    with pytest.raises(lut_image.LutImageError, match="first and last cell of every row"):
        lut_image.encode(6, TORQUE, SPEED, UDC, *arrays(thetas), map_id=1, cell_format="int11-sparse", stored=stored)
    flags = np.full(SHAPE, lut_image.FLAG_OK)
    flags[0, 1, 0] = lut_image.FLAG_NONE
    stored = np.ones(SHAPE, dtype=bool)
    stored[0, 2, 0] = False  # next to a cell without an entry
    with pytest.raises(lut_image.LutImageError, match="derived from a cell without an entry"):
        lut_image.encode(
            6, TORQUE, SPEED, UDC, *arrays(thetas), flags, map_id=1, cell_format="int11-sparse", stored=stored
        )
    blob = bytearray(lut_image.encode(6, TORQUE, SPEED, UDC, *arrays(thetas), map_id=1, cell_format="int11-sparse"))
    bitmap_at = lut_image.HEADER.size + 4 * (len(TORQUE) + len(SPEED) + 1) + 4
    blob[bitmap_at + 1] |= 0x80  # bit 15 of 10 cells
    body = bytes(blob[:-4])
    with pytest.raises(lut_image.LutImageError, match="bits set past the last cell"):
        lut_image.decode(body + struct.pack("<I", zlib.crc32(body)))
    short = lut_image.encode(6, TORQUE, SPEED, UDC, *arrays(thetas), map_id=1, cell_format="int11-sparse")[:-7]
    with pytest.raises(lut_image.LutImageError, match="length"):  # a stored cell missing
        lut_image.decode(short + struct.pack("<I", zlib.crc32(short)))


def test_the_encoder_leaves_out_exactly_the_cells_the_row_reproduces_within_the_bar():
    # a straight row (cartesian): only its ends are needed
    line = [complex(0.02 + 0.001 * j, -0.01) for j in range(6)]
    speeds = [1000.0 + 100.0 * j for j in range(6)]
    assert row_stored(speeds, line, 36.0, "cartesian") == [True, False, False, False, False, True]
    # one bump e at the middle of three: the straight line misses it by e, |theta| there is 0.02 + e
    for e, bar in ((0.0002, 36.0), (0.0005, 36.0)):
        row = [0.02 + 0j, complex(0.02 + e), 0.02 + 0j]
        suppression = 20.0 * math.log10((0.02 + e) / e)
        assert row_stored(speeds[:3], row, bar, "cartesian") == [True, suppression < bar, True]
    # a cell without an entry, or of another flag, is stored and stops the row's interpolation there
    assert row_stored(speeds, [*line[:2], None, *line[3:]], 36.0, "cartesian") == [True, True, True, True, False, True]
    flags = [1, 1, 1, 2, 2, 2]
    assert row_stored(speeds, line, 36.0, "cartesian", flags) == [True, False, True, True, False, True]


def sparse_map(max_bytes: int | None = None) -> dict:
    """A map whose theta* turns fast at 1 Nm around 1200 rpm and is straight elsewhere, int11-sparse cells."""
    speeds = [1000.0 + 25.0 * j for j in range(17)]
    cells = []
    for t in (1.0, 2.0, 3.0):
        for n in speeds:
            turn = 1.0 if t == 1.0 else 0.0
            theta = polar(2.0 + 0.2 * t, 40.0 + 0.05 * (n - 1000.0) + turn * 80.0 * math.tanh((n - 1200.0) / 40.0))
            cells.append(
                {
                    "torque_nm": t,
                    "speed_rpm": n,
                    "udc_v": 12.0,
                    "status": "ok",
                    "theta_cos": theta.real,
                    "theta_sin": theta.imag,
                }
            )
    provenance = {"lut_cells": "int11-sparse", **({"lut_max_bytes": max_bytes} if max_bytes else {})}
    return {
        "id": 9,
        "harmonic_order": 6,
        "axes": {"torque_nm": [1.0, 2.0, 3.0], "speed_rpm": speeds, "udc_v": [12.0]},
        "cells": cells,
        "provenance": provenance,
    }


def test_a_sparse_maps_image_holds_every_cell_within_the_bar_and_fits_its_budget():
    m = sparse_map()
    lut = lut_image.decode(service_image(m, interpolation="polar"))
    assert lut.format_version == lut_image.FORMAT_VERSION_SPARSE
    rows_stored = lut.stored[0].sum(axis=0)  # per torque row
    # the straight rows (2, 3 Nm: delta linear in speed, gamma constant) need only their ends; the turning row more
    assert list(rows_stored[1:]) == [2, 2] and rows_stored[0] > 4
    worst = math.inf
    for c in m["cells"]:
        theta = complex(c["theta_cos"], c["theta_sin"])
        error = abs(complex(*lut.theta(c["torque_nm"], c["speed_rpm"], 12.0)) - theta)
        worst = min(worst, 20.0 * math.log10(abs(theta) / error) if error else math.inf)
    assert worst >= 36.0 - 3.0  # the bar, less the int11 rounding (half a quantum of 1/1023 of full scale)
    size = len(service_image(m, interpolation="polar"))
    assert size == image_bytes(m["axes"], "int11-sparse", int(lut.stored.sum()))
    # a budget under that size: cells left out at a lower bar until the image fits
    small = service_image(sparse_map(max_bytes=size - 9), interpolation="polar")
    assert len(small) <= size - 9 and lut_image.decode(small).stored.sum() < lut.stored.sum()
    # a budget over it is spent: a higher bar stores more cells; one that holds every cell stores every cell
    every = image_bytes(m["axes"], "int11-sparse")
    roomy = lut_image.decode(service_image(sparse_map(max_bytes=(size + every) // 2), interpolation="polar"))
    assert lut.stored.sum() < roomy.stored.sum() < lut.stored.size
    assert len(service_image(sparse_map(max_bytes=(size + every) // 2), interpolation="polar")) <= (size + every) // 2
    assert lut_image.decode(service_image(sparse_map(max_bytes=every), interpolation="polar")).stored.all()


def test_a_cubic_image_is_never_sparse():
    thetas = random_thetas(3)
    with pytest.raises(lut_image.LutImageError, match="cubic"):
        lut_image.encode(
            6, TORQUE, SPEED, UDC, *arrays(thetas), map_id=5, interpolation="cubic", cell_format="int11-sparse"
        )
