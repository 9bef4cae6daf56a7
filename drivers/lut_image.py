"""The LUT image the drive takes on 0x2001:1 (docs/interfaces.md "LUT image"): encode, decode, interpolate.

One definition for both ends of the wire: the service builds the image from a map
(service/maps/lut_export.py) and the emulated drive firmware decodes it and interpolates with `Lut.theta`
(plant_emulator/drive_firmware.py). The exported C header carries the same interpolation in C for the
firmware (service/maps/lut_export.py export_c, `ripplecal_lut_map<ID>_theta`): a change to `Lut.theta` is a
change there too (tests/unit/test_lut_c_interpolator.py compares the two).

Layout, format_version 3 and 4 (little-endian, 20-byte header):
    magic "RCL1" | u16 format_version = 3 or 4 | u8 harmonic_order | u8 interpolation (0 cartesian, 1 polar) |
    u16 n_torque, n_speed, n_udc | u16 reserved = 0 | u32 map_id (>= 1) |
    f32 torque_nm[n_torque], speed_rpm[n_speed], udc_v[n_udc]  (each axis its own strictly increasing
        breakpoints: non-uniform spacing is interpolated by position) |
    f32 theta_cos_rad[n_udc][n_speed][n_torque] | f32 theta_sin_rad[...] |
    u8 flag[...]  (0 no entry: theta 0, no injection; 1 ok: a result at its target; 2 filled: a fill,
                   service/maps/fill.py; 3 injection off, version 4 only: the drive injects nothing in
                   any interval that has this cell as a corner of non-zero weight, theta kept for the
                   record) |
    u32 crc32 (zlib) of every byte before it.
Version 5 (cell_format "int16", 5 bytes a cell instead of 9: twice the cells in the same firmware memory) is
version 4 with theta as integers: after the axes, f32 theta_quantum_rad (> 0), then i16 theta_cos_q[...],
i16 theta_sin_q[...] (theta = q * theta_quantum_rad; the encoder takes the quantum as the largest |theta
component| of the map / 32767, so a 3 deg map has a quantum of 1.6e-6 rad, 86 dB under theta), then the flags
as in version 4.
Version 6 (cell_format "int11", 3 bytes a cell) packs each cell in one 24-bit little-endian word, after the axes
and the f32 theta_quantum_rad: bits 0-10 theta_cos_q, bits 11-21 theta_sin_q (each an 11-bit two's complement
integer in -1023 .. 1023, the quantum the largest |theta component| / 1023), bits 22-23 the flag as in version 4;
no flag array. The rounding error is at most half a quantum per component: for a cell at a tenth of the map's
largest |theta| 20 log10(0.1 * 1023 * sqrt 2) = 43 dB under it, beyond what identification reaches at most
cells; for twice the cells of int16 in the same firmware memory (measured on paper-bench's refined map: the
rounding alone leaves a median 62 dB and a minimum 33 dB under the cell's theta).
Version 7 (cell_format "int11-sparse": per-row speed breakpoints on one shared axis) is version 6 storing only some
cells: after the f32 theta_quantum_rad, u8 stored[ceil(cells / 8)] (bit i of byte i // 8, least significant
first, for cell i in [udc][speed][torque] order: 1 stored), then the 24-bit words of the stored cells only, in
index order. A row is the cells of one torque and U_dc along speed; its first and last cells are stored, and a
cell not stored (derived) lies between the row's nearest stored cells a and b (both entries, flag 1 or 2): the
drive gives it the interpolation of a and b by position along speed in the image's mode (`between`), flag 1
where both are flag 1, else 2. The drive's theta along that row is then exactly the interpolation between a and
b (cartesian: linear of linear; polar: gamma linear and delta on one unwrapped arc): each row has its own speed
breakpoints, and a breakpoint costs a cell only in the rows that need it (the field-weakening turn moves with
torque, measured: a shared axis spent most of 2048 bytes on cells that rows far from their turn interpolate).
Version 8 (several orders, issue 28) carries one image per harmonic order the drive injects at once:
    magic "RCL1" | u16 format_version = 8 | u8 n_orders (2 .. MAX_ORDERS) | u8 reserved = 0 | u32 map_id |
    n_orders x (u32 length | a whole single-order image of version 3 to 7, its own header (its harmonic order, the
        same map id), cells and CRC) |
    u32 crc32 (zlib) of every byte before it.
The first image is the map's own order (the drive's 0x2000:1); the orders are distinct. Each order interpolates
its own image by its own mode (`Lut.theta`); the drive then scales every order's theta by one factor so that the
sum of their |theta| is at most gamma_max (the injected angle is their sum, eq. 2-4). `decode` returns the first
order's Lut with the others in `further` and the container's CRC; a single-order image decodes as before (no
further orders).
Version 4 is version 3 plus flag 3 (FLAG_OFF); version 2 is the same layout with byte 7 reserved (0) and
u8 valid[...] (0/1) for the flags. The drive decodes all three: a version 2 image is flags = valid and
cartesian interpolation. `encode` writes version 4 only when a cell carries FLAG_OFF, else version 3
(so an image without off cells is byte for byte what it was before version 4, CRC included).
The image's CRC is that trailer: CRC-32 of the image WITHOUT its CRC field (`image_crc`). It is what
the drive reports on 0x2001:2 and what the service compares; a CRC-32 over the whole image,
trailer included, would be the constant residue 0x2144DF1C for every image. The map id (version 2 on)
is what the drive reports on 0x2001:4.

Interpolation (the drive, in injection mode 2; the paper's conventions: theta = [theta_cos, theta_sin],
gamma = |theta|, delta = -atan2(theta_sin, theta_cos), so theta_cos = gamma cos delta and
theta_sin = -gamma sin delta). The drive injects at flag 1 and 2 cells; a flag 0 cell has no entry.
Per axis, x clamped to [x_0, x_last] (the axis ends); in the interval x_j <= x < x_j+1 the weights by
position are f = (x - x_j) / (x_j+1 - x_j): w_j = 1 - f, w_j+1 = f (a one-value axis: weight 1).
The corners c of the enclosing cell carry w_c = w_torque w_speed w_udc (sum 1; corners of weight 0 drop).
- injection off (every mode, first): any corner of weight > 0 at flag 3 gives theta = (0, 0) exactly: no
  compensation there, never worse than none (near the field-weakening turn theta* passes near zero and
  turns fast, and an interpolated theta can miss it by more than |theta*|). On a grid line or point
  where the off corner's weight is 0 the other corners interpolate as usual.
- cartesian (mode 0): theta_cos = sum_c w_c theta_cos_c, theta_sin = sum_c w_c theta_sin_c, with
  theta_c = 0 at corners without an entry (multilinear in theta, as version 2 did).
- polar (mode 1): gamma = sum_c w_c gamma_c, with gamma_c = 0 at corners without an entry. The phase
  is averaged over E, the corners with an entry and gamma_c > 0 (a zero theta has no phase): reference
  r = the corner of E with the largest w_c (the first in [udc][speed][torque] index order on a tie);
  each delta_c is unwrapped to within +-pi of delta_r (the shortest arc):
      delta'_c = delta_r + ((delta_c - delta_r + pi) mod 2 pi) - pi
  and delta = sum_{c in E} w_c delta'_c / sum_{c in E} w_c (weights renormalised over E);
  theta_cos = gamma cos delta, theta_sin = -gamma sin delta. E empty: theta = 0.
  E.g. gamma 3 deg at delta 0 and 90 deg, midway: cartesian gives gamma 3 cos 45 deg at 45 deg, polar
  3 deg at 45 deg; delta 350 and 10 deg midway: polar 0 deg (not 180).
- cubic (mode 2): a cubic Hermite of theta (cartesian) along speed in each row (the cells of one torque and
  U_dc), then across torque over those rows' values at the speed, then linear across U_dc. On an axis, in the
  interval x_j <= x < x_j+1 (h = x_j+1 - x_j, f as above) with values v:
      H(x) = (1 + 2f)(1 - f)^2 v_j + f (1 - f)^2 h m_j + f^2 (3 - 2f) v_j+1 + f^2 (f - 1) h m_j+1
  each corner's slope m_k the three-point derivative of a non-uniform axis
      m_k = (h_r d_l + h_l d_r) / (h_l + h_r)   (d_l, d_r the secants to the values left and right of k,
                                                  h_l, h_r their widths)
  where the values k - 1, k and k + 1 are all whole, else the interval's own secant (v_j+1 - v_j) / h (an axis
  end, a neighbour not whole: never a value outside the interval's corners acts beyond its slope). Along speed a
  value is whole at a cell with an entry; a corner without one makes the row cartesian's linear blend there
  (theta_c = 0). Across torque a row's value is whole where its speed corners of weight > 0 are entries; a
  corner row not whole makes it linear across torque there. The turn at the field-weakening onset is a loop of
  theta* along speed and moves with torque: theta* identified every 5 rpm over 1900..2500 rpm at 1..3 Nm
  (seed 5) holds 30 dB between breakpoints 25 rpm apart at 98.3 % of the points cubic, 89.5 % polar and
  88.9 % cartesian; every 12.5 rpm and 0.0625 Nm over 2050..2300 rpm, between rows 0.25 Nm and speeds 12.5 rpm
  apart, 97.6 % cubic across torque too against 90.9 % linear across torque and 91.3 % polar
  (docs/interfaces.md, "LUT image").
The drive then clamps |theta| to gamma_max (0x2000:5).
"""

from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass, replace
from functools import cached_property
from typing import Literal

import numpy as np

MAGIC = b"RCL1"
FORMAT_VERSION = 3  # what encode writes for a map without injection-off cells
FORMAT_VERSION_OFF = 4  # what encode writes when a cell carries FLAG_OFF
FORMAT_VERSION_INT16 = 5  # what encode writes for cell_format "int16" (any flag)
FORMAT_VERSION_INT11 = 6  # what encode writes for cell_format "int11" (any flag)
FORMAT_VERSION_SPARSE = 7  # what encode writes for cell_format "int11-sparse" (stored cells and a bitmap)
FORMAT_VERSION_ORDERS = 8  # several orders: one single-order image per order in a container
SUPPORTED_VERSIONS = (2, 3, 4, 5, 6, 7, 8)  # what the drive decodes
MAX_ORDERS = 4  # the drive injects its own order and up to 3 further ones (0x2002)
ORDERS_HEADER = struct.Struct("<4sHBBI")  # magic, version 8, n_orders, reserved, map_id
LENGTH = struct.Struct("<I")
# theta per cell: f32 (versions 2-4), i16 (version 5) or packed 11-bit integers (version 6) times one quantum
CELL_FORMATS = ("float32", "int16", "int11", "int11-sparse")
# theta_cos, theta_sin and the flag (int11-sparse: a stored cell, plus one bit a cell for the bitmap)
CELL_BYTES = {"float32": 9, "int16": 5, "int11": 3, "int11-sparse": 3}
FULL_SCALE = {"int16": 32767, "int11": 1023, "int11-sparse": 1023}  # the integer cells' largest |q|
SPARSE = "int11-sparse"
INT16_FULL_SCALE = FULL_SCALE["int16"]
INT11_BITS = 11
HEADER = struct.Struct("<4sHBBHHHHI")
TRAILER = struct.Struct("<I")  # CRC-32 (zlib) of every byte before it
MAX_CELLS = 4096
AXES = ("torque_nm", "speed_rpm", "udc_v")
MAX_MAP_ID = 0xFFFFFFFF  # u32; 0 is what the drive reports when it holds no LUT

# per-cell flag byte
FLAG_NONE, FLAG_OK, FLAG_FILLED, FLAG_OFF = 0, 1, 2, 3
FLAGS = (FLAG_NONE, FLAG_OK, FLAG_FILLED, FLAG_OFF)
# the flags each format version knows
VERSION_FLAGS = {
    2: (FLAG_NONE, FLAG_OK),
    3: (FLAG_NONE, FLAG_OK, FLAG_FILLED),
    4: FLAGS,
    5: FLAGS,
    6: FLAGS,
    7: FLAGS,
}
# the header's interpolation byte: the code is the index
INTERPOLATIONS = ("cartesian", "polar", "cubic")
Interpolation = Literal["cartesian", "polar", "cubic"]  # a request's field: one of INTERPOLATIONS
# what a download uses unless it names one: polar, measured to hold better where theta* turns (the
# field-weakening turn): 5 x 11 probe maps, 1..4 Nm x 1000..2600 rpm at 12 V, validated in LUT mode both
# ways, paper-bench and seeds 1-3: points >= 30 dB 128/132/129/126 of 189 polar against 121/124/123/114
# cartesian, the same order across field weakening (docs/interfaces.md, "LUT image")
DEFAULT_INTERPOLATION = "polar"


class LutImageError(ValueError):
    """The image is malformed or cannot be built (the drive answers SDO abort 0x08000020)."""


@dataclass(frozen=True)
class Lut:
    """A decoded image: map id, axes, theta per cell [udc][speed][torque] (0 where flag 0; an off cell's
    theta is kept for the record, never injected), the flag per cell, the interpolation mode, the
    image's format version and CRC."""

    map_id: int
    harmonic_order: int
    torque_nm: np.ndarray  # (n_t,)
    speed_rpm: np.ndarray  # (n_n,)
    udc_v: np.ndarray  # (n_u,)
    theta_cos: np.ndarray  # (n_u, n_n, n_t), rad, 0 where flag 0
    theta_sin: np.ndarray
    flags: np.ndarray  # uint8 (n_u, n_n, n_t): FLAG_NONE | FLAG_OK | FLAG_FILLED | FLAG_OFF
    crc: int  # image_crc: CRC-32 of the image without its CRC field
    interpolation: str = DEFAULT_INTERPOLATION
    format_version: int = FORMAT_VERSION
    stored: np.ndarray | None = None  # bool per cell (version 7): False where the drive derived it; None: all stored
    further: tuple["Lut", ...] = ()  # version 8: the further orders' LUTs, each interpolated on its own

    @property
    def orders(self) -> tuple[int, ...]:
        """The harmonic orders the image carries, its own first."""
        return (self.harmonic_order, *(lut.harmonic_order for lut in self.further))

    @property
    def valid(self) -> np.ndarray:
        """bool per cell: an ok entry (flag 1)."""
        return self.flags == FLAG_OK

    @property
    def filled(self) -> np.ndarray:
        """bool per cell: a filled entry (flag 2)."""
        return self.flags == FLAG_FILLED

    @property
    def injection_off(self) -> np.ndarray:
        """bool per cell: injection off around it (flag 3)."""
        return self.flags == FLAG_OFF

    @property
    def entry(self) -> np.ndarray:
        """bool per cell: the drive injects there (flag 1 or 2)."""
        return (self.flags == FLAG_OK) | (self.flags == FLAG_FILLED)

    @cached_property
    def _gamma_delta(self) -> tuple[np.ndarray, np.ndarray]:
        # delta = -atan2(theta_sin, theta_cos) (eq. 22), rad
        return np.hypot(self.theta_cos, self.theta_sin), -np.arctan2(self.theta_sin, self.theta_cos)

    def theta(self, torque_nm: float, speed_rpm: float, udc_v: float) -> tuple[float, float]:
        """(theta_cos, theta_sin) in rad at an operating point, interpolated by the image's mode and
        clamped at the axis ends (module doc has the formulas); not yet clamped to gamma_max."""
        corners = [
            ((iu, i_n, it), wu * wn * wt)
            for (iu, wu) in _weights(self.udc_v, udc_v)
            for (i_n, wn) in _weights(self.speed_rpm, speed_rpm)
            for (it, wt) in _weights(self.torque_nm, torque_nm)
            if wu * wn * wt != 0.0
        ]
        if any(self.flags[c] == FLAG_OFF for c, _ in corners):
            return 0.0, 0.0  # injection off: exactly no compensation (module doc)
        if self.interpolation == "polar":
            return self._polar(corners)
        if self.interpolation == "cubic":
            theta = sum(
                wu * self._across_torque(iu, torque_nm, speed_rpm)
                for (iu, wu) in _weights(self.udc_v, udc_v)
                if wu != 0.0
            )
            return float(theta.real), float(theta.imag)
        tc = sum(w * float(self.theta_cos[c]) for c, w in corners)  # 0 where flag 0 (decode)
        ts = sum(w * float(self.theta_sin[c]) for c, w in corners)
        return float(tc), float(ts)

    def _row(self, iu: int, it: int, speed_rpm: float) -> tuple[complex, bool]:
        """theta along speed in the row of (iu, it), cubic (module doc), and whether it is whole: every speed corner
        of weight > 0 an entry."""
        entry = self.entry[iu, :, it]
        row = [
            complex(c, s) if e else None
            for c, s, e in zip(self.theta_cos[iu, :, it], self.theta_sin[iu, :, it], entry, strict=True)
        ]
        whole = all(row[i] is not None for i, w in _weights(self.speed_rpm, speed_rpm) if w != 0.0)
        return along_row(self.speed_rpm, row, speed_rpm, "cubic"), whole

    def _across_torque(self, iu: int, torque_nm: float, speed_rpm: float) -> complex:
        """The rows' theta at speed_rpm interpolated across torque, cubic (module doc): the Hermite of the two
        torque corners' rows, each slope from the rows beside it where they are whole, else linear."""
        corners = _weights(self.torque_nm, torque_nm)
        j = corners[0][0]
        if len(corners) == 1:  # at an axis end or a one-value axis: that row
            return self._row(iu, j, speed_rpm)[0]
        near = {k: self._row(iu, k, speed_rpm) for k in range(j - 1, j + 3) if 0 <= k < len(self.torque_nm)}
        if not (near[j][1] and near[j + 1][1]):
            return sum(w * near[k][0] for k, w in corners)  # a corner not whole: linear, as cartesian
        column: list[complex | None] = [None] * len(self.torque_nm)
        for k, (value, whole) in near.items():
            column[k] = value if whole else None
        return along_row(self.torque_nm, column, torque_nm, "cubic")

    def _polar(self, corners) -> tuple[float, float]:
        gamma_c, delta_c = self._gamma_delta
        with_phase = [
            (c, w) for c, w in corners if self.flags[c] != FLAG_NONE and gamma_c[c] > 0.0
        ]  # off: theta returned 0
        if not with_phase:
            return 0.0, 0.0
        gamma = sum(w * float(gamma_c[c]) for c, w in with_phase)  # no entry: gamma 0
        ref = float(delta_c[max(with_phase, key=lambda cw: cw[1])[0]])  # first of the largest weight
        total = sum(w for _, w in with_phase)
        # each corner's delta within +-pi of the reference's: the shortest arc
        delta = (
            sum(w * (ref + (float(delta_c[c]) - ref + math.pi) % (2.0 * math.pi) - math.pi) for c, w in with_phase)
            / total
        )
        return gamma * math.cos(delta), -gamma * math.sin(delta)


def _signed11(words: np.ndarray) -> np.ndarray:
    """The low 11 bits of each word as a two's complement integer (float64)."""
    low = words & ((1 << INT11_BITS) - 1)
    return np.where(low >= 1 << (INT11_BITS - 1), low - (1 << INT11_BITS), low).astype(np.float64)


def between(theta_a: complex, theta_b: complex, x_a: float, x_b: float, x: float, interpolation: str) -> complex:
    """theta at x between two breakpoints x_a < x_b of one axis that carry theta_a and theta_b (entries): `Lut.theta`'s
    rule (module doc) with these two corners, in closed form (a derived cell of a version 7 row, and the placement's
    prediction; tests/unit/test_lut_sparse.py holds it to Lut.theta). "cubic": the two corners' linear blend, as
    cartesian (the Hermite needs the corners' neighbours: `along_row`)."""
    f = 0.0 if not math.isfinite(x) or x <= x_a else (1.0 if x >= x_b else (x - x_a) / (x_b - x_a))
    corners = [(t, w) for t, w in ((theta_a, 1.0 - f), (theta_b, f)) if w != 0.0]
    if interpolation != "polar":
        return complex(sum(w * t for t, w in corners))
    with_phase = [(t, w) for t, w in corners if abs(t) > 0.0]
    if not with_phase:
        return 0j
    gamma = sum(w * abs(t) for t, w in with_phase)
    ref_theta = max(with_phase, key=lambda tw: tw[1])[0]  # the first of the largest weight
    ref = -math.atan2(ref_theta.imag, ref_theta.real)
    total = sum(w for _, w in with_phase)
    delta = (
        sum(
            w * (ref + (-math.atan2(t.imag, t.real) - ref + math.pi) % (2.0 * math.pi) - math.pi) for t, w in with_phase
        )
        / total
    )
    return complex(gamma * math.cos(delta), -gamma * math.sin(delta))


def along_row(xs, row: list[complex | None], x: float, interpolation: str) -> complex:
    """theta at x along one axis whose breakpoints `xs` (strictly increasing) carry `row` (None: not whole, theta 0),
    by the drive's rule (module doc; clamped at the ends): `between` of the interval's two corners, or in "cubic"
    the Hermite with each corner's slope from its neighbours (Lut.theta's rows and columns, and the placement's
    prediction along either axis)."""
    weights = _weights(np.asarray(xs, dtype=float), x)
    if len(weights) == 1:
        return row[weights[0][0]] or 0j
    j = weights[0][0]
    a, b = row[j], row[j + 1]
    x_a, x_b = float(xs[j]), float(xs[j + 1])
    if interpolation != "cubic" or a is None or b is None:  # a corner without an entry: theta 0 there
        return between(0j if a is None else a, 0j if b is None else b, x_a, x_b, x, interpolation)
    h = x_b - x_a
    secant = (b - a) / h
    m_a, m_b = secant, secant
    if j > 0 and row[j - 1] is not None:
        h_l = x_a - float(xs[j - 1])
        m_a = (h * (a - row[j - 1]) / h_l + h_l * secant) / (h_l + h)  # type: ignore[operator]
    if j + 2 < len(row) and row[j + 2] is not None:
        h_r = float(xs[j + 2]) - x_b
        m_b = (h_r * secant + h * (row[j + 2] - b) / h_r) / (h + h_r)  # type: ignore[operator]
    f = weights[1][1]
    return (
        (1 + 2 * f) * (1 - f) ** 2 * a
        + f * (1 - f) ** 2 * h * m_a
        + f * f * (3 - 2 * f) * b
        + f * f * (f - 1) * h * m_b
    )


def check_stored(stored: np.ndarray, flags: np.ndarray) -> None:
    """LutImageError unless every row (the cells of one torque and U_dc along speed, [udc][speed][torque]) stores
    its first and last cell, and every cell not stored lies between stored entries (flag 1 or 2) and is one itself
    (an off cell, or one without an entry, is always stored)."""
    entry = (flags == FLAG_OK) | (flags == FLAG_FILLED)
    if not (np.all(stored[:, 0, :]) and np.all(stored[:, -1, :])):
        raise LutImageError("the first and last cell of every row along speed must be stored")
    nu, nn, nt = stored.shape
    for iu in range(nu):
        for it in range(nt):
            last = 0
            for j in range(1, nn):
                if not stored[iu, j, it]:
                    if not entry[iu, j, it]:
                        raise LutImageError(f"cell [{iu}][{j}][{it}] is not stored but is not an entry")
                    continue
                if j - last > 1 and not (entry[iu, last, it] and entry[iu, j, it]):
                    raise LutImageError(
                        f"cells between [{iu}][{last}][{it}] and [{iu}][{j}][{it}] are derived from a cell without "
                        "an entry"
                    )
                last = j


def _derive_rows(lut_axes: tuple[np.ndarray, np.ndarray, np.ndarray], tc, tsn, flags, stored, mode: str) -> None:
    """Fill the cells not stored (in place) with the interpolation of their row's nearest stored cells (module doc)."""
    speed = lut_axes[1]
    nu, nn, nt = stored.shape
    for iu in range(nu):
        for it in range(nt):
            kept = [j for j in range(nn) if stored[iu, j, it]]
            for a, b in zip(kept, kept[1:]):
                theta_a, theta_b = complex(tc[iu, a, it], tsn[iu, a, it]), complex(tc[iu, b, it], tsn[iu, b, it])
                both_ok = flags[iu, a, it] == FLAG_OK and flags[iu, b, it] == FLAG_OK
                for j in range(a + 1, b):
                    theta = between(theta_a, theta_b, float(speed[a]), float(speed[b]), float(speed[j]), mode)
                    tc[iu, j, it], tsn[iu, j, it] = theta.real, theta.imag
                    flags[iu, j, it] = FLAG_OK if both_ok else FLAG_FILLED


def _pack11(qc: np.ndarray, qs: np.ndarray, f: np.ndarray) -> bytes:
    """Cells as 24-bit little-endian words: bits 0-10 theta_cos_q, 11-21 theta_sin_q, 22-23 the flag."""
    mask = (1 << INT11_BITS) - 1
    words = (
        (qc.astype(np.int64).ravel() & mask)
        | ((qs.astype(np.int64).ravel() & mask) << INT11_BITS)
        | (f.astype(np.int64).ravel() << (2 * INT11_BITS))
    )
    return words.astype("<u4").view(np.uint8).reshape(-1, 4)[:, :3].tobytes()


def _weights(axis: np.ndarray, x: float) -> list[tuple[int, float]]:
    """(index, weight) of the breakpoints around x, by position on a non-uniform axis; clamped."""
    n = len(axis)
    if n == 1 or not math.isfinite(x) or x <= axis[0]:
        return [(0, 1.0)]
    if x >= axis[-1]:
        return [(n - 1, 1.0)]
    j = int(np.searchsorted(axis, x, side="right")) - 1
    f = (x - float(axis[j])) / (float(axis[j + 1]) - float(axis[j]))
    return [(j, 1.0 - f), (j + 1, f)]


def image_crc(blob: bytes) -> int:
    """The image's CRC: CRC-32 (zlib) of every byte but the trailing CRC field (docs/interfaces.md)."""
    return _crc32(bytes(blob)[: -TRAILER.size])


def crc_hex(crc: int) -> str:
    """A CRC as the service shows it everywhere (API, CLI, dashboard): 0x and 8 upper-case hex digits."""
    return f"0x{int(crc):08X}"


def _crc32(body: bytes) -> int:
    return zlib.crc32(body) & 0xFFFFFFFF


def check_interpolation(interpolation: str | None) -> str:
    """The mode named (None: DEFAULT_INTERPOLATION); LutImageError for a name not in INTERPOLATIONS."""
    mode = DEFAULT_INTERPOLATION if interpolation is None else interpolation
    if mode not in INTERPOLATIONS:
        raise LutImageError(f"interpolation {mode!r} is not one of {', '.join(INTERPOLATIONS)}")
    return mode


def encode(
    harmonic_order: int,
    torque_nm,
    speed_rpm,
    udc_v,
    theta_cos,
    theta_sin,
    flags=None,
    *,
    map_id: int,
    interpolation: str | None = None,
    cell_format: str = "float32",
    stored=None,
) -> bytes:
    """A format_version 3 image of map `map_id` (4 when a cell carries FLAG_OFF) from the axes and
    [udc][speed][torque] arrays (nested lists or arrays of that shape, or flat in that order). flags:
    FLAG_NONE / FLAG_OK / FLAG_FILLED / FLAG_OFF per cell (default all FLAG_OK); cells with flag 0 go in
    with theta 0, off cells with their theta (for the record). interpolation: "cartesian", "polar" or "cubic"
    (None: DEFAULT_INTERPOLATION; "cubic" not with "int11-sparse", whose derived cells are two-corner blends). cell_format "int16" / "int11": a version 5 / 6 image (module doc);
    "int11-sparse": version 7, storing the cells where `stored` (bool per cell, default all) is true. Raises
    LutImageError if the map has more than MAX_CELLS
    cells, an axis is not strictly increasing, a flag or theta is not allowed, or map_id is not in
    1 .. MAX_MAP_ID."""
    if not 1 <= int(map_id) <= MAX_MAP_ID:
        raise LutImageError(f"map_id {map_id} is not in 1 .. {MAX_MAP_ID} (0 means no LUT)")
    mode = check_interpolation(interpolation)
    if mode == "cubic" and cell_format == SPARSE:
        raise LutImageError(
            "cubic interpolation takes every cell of a row (each corner's slope comes from its neighbours): "
            "an int11-sparse image derives cells from two; use int11, int16 or float32 cells"
        )
    axes = (torque_nm, speed_rpm, udc_v)
    nt, nn, nu = (len(a) for a in axes)
    if nt * nn * nu > MAX_CELLS:
        raise LutImageError(f"map has {nt * nn * nu} cells; the drive takes at most {MAX_CELLS}")
    for name, axis in zip(AXES, axes):
        if any(b <= a for a, b in zip(axis, axis[1:])):
            raise LutImageError(f"axis {name} is not strictly increasing")
    shape = (nu, nn, nt)
    f = np.full(shape, FLAG_OK, dtype=np.uint8) if flags is None else np.asarray(flags).reshape(shape)
    if not np.all(np.isin(f, FLAGS)):
        raise LutImageError(
            f"flags must be {FLAG_NONE} (no entry), {FLAG_OK} (ok), {FLAG_FILLED} (filled) or {FLAG_OFF} (injection off)"
        )
    f = f.astype(np.uint8)
    if cell_format not in CELL_FORMATS:
        raise LutImageError(f"cell_format {cell_format!r} is not one of {', '.join(CELL_FORMATS)}")
    version = format_version_of(f, cell_format)
    tc = np.where(f == FLAG_NONE, 0.0, np.asarray(theta_cos, dtype=np.float64).reshape(shape))
    tsn = np.where(f == FLAG_NONE, 0.0, np.asarray(theta_sin, dtype=np.float64).reshape(shape))
    if not (np.all(np.isfinite(tc)) and np.all(np.isfinite(tsn))):
        raise LutImageError("theta values not finite")
    body = HEADER.pack(MAGIC, version, int(harmonic_order), INTERPOLATIONS.index(mode), nt, nn, nu, 0, int(map_id))
    for axis in axes:
        body += np.asarray(axis, dtype="<f4").tobytes()
    if cell_format in FULL_SCALE:
        quantum = theta_quantum(tc, tsn, cell_format)
        body += np.float32(quantum).astype("<f4").tobytes()
        qc, qs = quantized(tc, quantum, cell_format), quantized(tsn, quantum, cell_format)
        if cell_format == "int16":
            body += qc.tobytes() + qs.tobytes()
        elif cell_format == SPARSE:  # the bitmap, then the stored cells' words
            keep = np.ones(shape, dtype=bool) if stored is None else np.asarray(stored, dtype=bool).reshape(shape)
            check_stored(keep, f)
            body += np.packbits(keep.ravel(), bitorder="little").tobytes()
            body += _pack11(qc.ravel()[keep.ravel()], qs.ravel()[keep.ravel()], f.ravel()[keep.ravel()])
            return body + TRAILER.pack(_crc32(body))
        else:  # one 24-bit word a cell: the flag travels in it
            body += _pack11(qc, qs, f)
            return body + TRAILER.pack(_crc32(body))
    else:
        body += tc.astype("<f4").tobytes() + tsn.astype("<f4").tobytes()
    body += f.tobytes()
    return body + TRAILER.pack(_crc32(body))


def theta_quantum(theta_cos, theta_sin, cell_format: str = "int16") -> float:
    """The quantum of an integer-cell image (version 5 or 6), rad: the largest |theta component| / the format's full
    scale, as the f32 the image carries (rounded up, so no component overflows); 1.0 for a map of zeros."""
    full_scale = FULL_SCALE[cell_format]
    largest = float(max(np.max(np.abs(theta_cos), initial=0.0), np.max(np.abs(theta_sin), initial=0.0)))
    if largest == 0.0:
        return 1.0
    q = np.float32(largest / full_scale)
    return float(q if float(q) * full_scale >= largest else np.nextafter(q, np.float32(np.inf)))


def quantized(theta, quantum: float, cell_format: str = "int16") -> np.ndarray:
    """theta / quantum rounded to the nearest integer, as the i16 (version 5) or 11-bit integer (version 6) the
    image carries, as i16."""
    full_scale = FULL_SCALE[cell_format]
    return np.clip(np.rint(np.asarray(theta, dtype=np.float64) / quantum), -full_scale, full_scale).astype("<i2")


def format_version_of(flags, cell_format: str = "float32") -> int:
    """The format version `encode` writes for these flags and cells: FORMAT_VERSION_INT16 / _INT11 for int16 /
    int11 cells, else FORMAT_VERSION_OFF when any is FLAG_OFF, else FORMAT_VERSION (an image without off cells
    stays what it was before version 4)."""
    if cell_format == "int16":
        return FORMAT_VERSION_INT16
    if cell_format == "int11":
        return FORMAT_VERSION_INT11
    if cell_format == SPARSE:
        return FORMAT_VERSION_SPARSE
    return FORMAT_VERSION_OFF if np.any(np.asarray(flags) == FLAG_OFF) else FORMAT_VERSION


def encode_orders(images: list[bytes]) -> bytes:
    """A version 8 image of several orders from their single-order images (`encode`'s, the map's own order first;
    each of the same map id, the orders distinct). LutImageError says what does not fit."""
    if not 2 <= len(images) <= MAX_ORDERS:
        raise LutImageError(f"a several-order image carries 2 to {MAX_ORDERS} orders, not {len(images)}")
    luts = [decode(image) for image in images]
    _check_orders(luts)
    body = ORDERS_HEADER.pack(MAGIC, FORMAT_VERSION_ORDERS, len(images), 0, luts[0].map_id)
    for image in images:
        body += LENGTH.pack(len(image)) + bytes(image)
    return body + TRAILER.pack(_crc32(body))


def _check_orders(luts: list[Lut]) -> None:
    orders = [lut.harmonic_order for lut in luts]
    if len(set(orders)) != len(orders):
        raise LutImageError(f"orders {orders} name an order twice")
    if any(lut.further for lut in luts):
        raise LutImageError("an order's image is itself of several orders")
    ids = {lut.map_id for lut in luts}
    if len(ids) != 1:
        raise LutImageError(f"the orders' images carry map ids {sorted(ids)}, not one")


def _decode_orders(blob: bytes) -> Lut:
    """A version 8 image: the first order's Lut with the others in `further` and the container's CRC."""
    if len(blob) < ORDERS_HEADER.size + TRAILER.size:
        raise LutImageError(f"image too short ({len(blob)} bytes)")
    _magic, _version, n_orders, reserved, map_id = ORDERS_HEADER.unpack_from(blob, 0)
    if not 2 <= n_orders <= MAX_ORDERS:
        raise LutImageError(f"n_orders {n_orders} is not in 2 .. {MAX_ORDERS}")
    if reserved != 0:
        raise LutImageError(f"reserved header field is {reserved}, not 0")
    (crc_stored,) = TRAILER.unpack_from(blob, len(blob) - TRAILER.size)
    crc = image_crc(blob)
    if crc != crc_stored:
        raise LutImageError(f"CRC-32 mismatch: the trailer says {crc_hex(crc_stored)}, the image is {crc_hex(crc)}")
    luts, off, end = [], ORDERS_HEADER.size, len(blob) - TRAILER.size
    for k in range(n_orders):
        if off + LENGTH.size > end:
            raise LutImageError(f"image ends before order {k + 1} of {n_orders}")
        (length,) = LENGTH.unpack_from(blob, off)
        off += LENGTH.size
        if off + length > end:
            raise LutImageError(f"order {k + 1}'s image ({length} bytes) runs past the end")
        part = blob[off : off + length]
        try:
            luts.append(decode(part))
        except LutImageError as exc:
            raise LutImageError(f"order {k + 1}'s image: {exc}") from None
        off += length
    if off != end:
        raise LutImageError(f"{end - off} bytes after the last order's image")
    _check_orders(luts)
    if luts[0].map_id != map_id:
        raise LutImageError(f"the header's map id {map_id} is not its orders' ({luts[0].map_id})")
    return replace(luts[0], crc=crc, format_version=FORMAT_VERSION_ORDERS, further=tuple(luts[1:]))


def decode(blob: bytes) -> Lut:
    """Check and decode an image of format_version 2 to 8; LutImageError says what is wrong."""
    blob = bytes(blob)
    if len(blob) < 6:
        raise LutImageError(f"image too short ({len(blob)} bytes)")
    magic, version = struct.unpack_from("<4sH", blob, 0)
    if magic != MAGIC:
        raise LutImageError(f"bad magic {magic!r}")
    if version == FORMAT_VERSION_ORDERS:
        return _decode_orders(blob)
    if version not in SUPPORTED_VERSIONS:  # before the length: another version has another header
        raise LutImageError(
            f"unsupported format_version {version}: this drive takes versions "
            f"{', '.join(str(v) for v in SUPPORTED_VERSIONS[:-1])} and {SUPPORTED_VERSIONS[-1]} "
            "(their header carries the map id)"
        )
    if len(blob) < HEADER.size + TRAILER.size:
        raise LutImageError(f"image too short ({len(blob)} bytes)")
    _magic, _version, h, mode_code, nt, nn, nu, reserved, map_id = HEADER.unpack_from(blob, 0)
    if map_id == 0:
        raise LutImageError("map_id 0 is reserved (the drive reports 0 when it holds no LUT)")
    if h < 1:
        raise LutImageError("harmonic_order must be >= 1")
    allowed = VERSION_FLAGS[version]
    if version >= 3:
        if mode_code >= len(INTERPOLATIONS):
            raise LutImageError(f"interpolation {mode_code} unknown (0 cartesian, 1 polar, 2 cubic)")
        if reserved != 0:
            raise LutImageError(f"reserved header field is {reserved}, not 0")
        interpolation = INTERPOLATIONS[mode_code]
    else:  # version 2: byte 7 was reserved, the flags were valid 0/1; it interpolated cartesian
        interpolation = "cartesian"
    if min(nt, nn, nu) < 1 or nt * nn * nu > MAX_CELLS:
        raise LutImageError(f"bad axis lengths {nt} x {nn} x {nu}")
    cells = nt * nn * nu
    int16 = version == FORMAT_VERSION_INT16
    sparse = version == FORMAT_VERSION_SPARSE
    if sparse and interpolation == "cubic":
        raise LutImageError("a version 7 image cannot be cubic: its derived cells are two-corner blends")
    int11 = version == FORMAT_VERSION_INT11 or sparse
    stored = np.ones(cells, dtype=bool)
    bitmap_at = HEADER.size + 4 * (nt + nn + nu) + 4
    bitmap_bytes = (cells + 7) // 8 if sparse else 0
    if sparse:
        if len(blob) < bitmap_at + bitmap_bytes + TRAILER.size:
            raise LutImageError(f"image too short ({len(blob)} bytes) for the bitmap of {nt} x {nn} x {nu} cells")
        bits = np.frombuffer(blob, dtype=np.uint8, count=bitmap_bytes, offset=bitmap_at)
        unpacked = np.unpackbits(bits, bitorder="little")
        if np.any(unpacked[cells:]):
            raise LutImageError("the stored-cell bitmap has bits set past the last cell")
        stored = unpacked[:cells].astype(bool)
    n_words = int(np.count_nonzero(stored))
    # the quantum and two i16 per cell, or the quantum and one 24-bit word (flag included) per stored cell (and
    # the bitmap), or two f32; the flags
    if int16:
        cell_bytes = 4 + 5 * cells
    elif int11:
        cell_bytes = 4 + bitmap_bytes + 3 * n_words
    else:
        cell_bytes = 9 * cells
    expected = HEADER.size + 4 * (nt + nn + nu) + cell_bytes + TRAILER.size
    if len(blob) != expected:
        raise LutImageError(f"length {len(blob)} != {expected} for {nt} x {nn} x {nu}")
    (crc_stored,) = TRAILER.unpack_from(blob, len(blob) - TRAILER.size)
    crc = image_crc(blob)
    if crc != crc_stored:
        raise LutImageError(f"CRC-32 mismatch: the trailer says {crc_hex(crc_stored)}, the image is {crc_hex(crc)}")
    off = HEADER.size
    axes = []
    for n_ax, name in zip((nt, nn, nu), AXES):
        ax = np.frombuffer(blob, dtype="<f4", count=n_ax, offset=off).astype(np.float64)
        off += 4 * n_ax
        if not np.all(np.isfinite(ax)) or np.any(np.diff(ax) <= 0):
            raise LutImageError(f"axis {name} not finite and strictly increasing")
        axes.append(ax)
    if int16 or int11:
        (quantum,) = struct.unpack_from("<f", blob, off)
        off += 4
        if not (math.isfinite(quantum) and quantum > 0.0):
            raise LutImageError(f"theta_quantum_rad {quantum} is not a positive finite number")
    if int11:
        off += bitmap_bytes
        raw = np.frombuffer(blob, dtype=np.uint8, count=3 * n_words, offset=off).reshape(n_words, 3).astype(np.int64)
        off += 3 * n_words
        words = np.zeros(cells, dtype=np.int64)
        words[stored] = raw[:, 0] | (raw[:, 1] << 8) | (raw[:, 2] << 16)
        tc = (_signed11(words) * quantum).reshape(nu, nn, nt)
        tsn = (_signed11(words >> INT11_BITS) * quantum).reshape(nu, nn, nt)
        flags = (words >> (2 * INT11_BITS)).astype(np.uint8).reshape(nu, nn, nt)
    elif int16:
        tc = np.frombuffer(blob, dtype="<i2", count=cells, offset=off).astype(np.float64).reshape(nu, nn, nt) * quantum
        off += 2 * cells
        tsn = np.frombuffer(blob, dtype="<i2", count=cells, offset=off).astype(np.float64).reshape(nu, nn, nt) * quantum
        off += 2 * cells
    else:
        tc = np.frombuffer(blob, dtype="<f4", count=cells, offset=off).astype(np.float64).reshape(nu, nn, nt)
        off += 4 * cells
        tsn = np.frombuffer(blob, dtype="<f4", count=cells, offset=off).astype(np.float64).reshape(nu, nn, nt)
        off += 4 * cells
    if not int11:
        flags = np.frombuffer(blob, dtype=np.uint8, count=cells, offset=off).reshape(nu, nn, nt).copy()
    if not np.all(np.isin(flags, allowed)):
        raise LutImageError(f"flags must be one of {allowed} in a format_version {version} image")
    if not (np.all(np.isfinite(tc)) and np.all(np.isfinite(tsn))):
        raise LutImageError("theta values not finite")
    stored_cells = stored.reshape(nu, nn, nt)
    if sparse:  # the derived cells: checked like the encoder's, then interpolated along their rows
        flags[~stored_cells] = FLAG_OK  # not carried; set by _derive_rows
        check_stored(stored_cells, flags)
        _derive_rows((axes[0], axes[1], axes[2]), tc, tsn, flags, stored_cells, interpolation)
    entry = flags != FLAG_NONE  # an off cell keeps its theta (the record); Lut.theta never injects it
    return Lut(
        int(map_id),
        int(h),
        axes[0],
        axes[1],
        axes[2],
        np.where(entry, tc, 0.0),
        np.where(entry, tsn, 0.0),
        flags,
        crc,
        interpolation,
        int(version),
        stored_cells if sparse else None,
    )
