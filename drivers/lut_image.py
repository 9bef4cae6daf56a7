"""The LUT image the drive takes on 0x2001:1 (docs/interfaces.md "LUT image"): encode and decode.

One definition for both ends of the wire: the service builds the image from a map
(service/lut_export.py) and the emulated drive firmware decodes it (plant_emulator/drive_firmware.py).

Layout (little-endian):
    magic "RCL1" | u16 format_version = 2 | u8 harmonic_order | u8 reserved |
    u16 n_torque, n_speed, n_udc | u16 reserved | u32 map_id (>= 1) |
    f32 torque_nm[n_torque], speed_rpm[n_speed], udc_v[n_udc]  (strictly increasing) |
    f32 theta_cos_rad[n_udc][n_speed][n_torque] | f32 theta_sin_rad[...] | u8 valid[...] |
    u32 crc32 (zlib) of every byte before it.
The image's CRC is that trailer: CRC-32 of the image WITHOUT its CRC field (`image_crc`). It is what
the drive reports on 0x2001:2 and what the service compares; a CRC-32 over the whole image,
trailer included, would be the constant residue 0x2144DF1C for every image.
Version 2 added map_id (the drive reports it on 0x2001:4, so the bench knows which map it holds).
The drive interpolates theta_cos and theta_sin separately, multilinearly in (torque command, measured
speed, measured U_dc), clamped at the axis ends; invalid cells count as theta = 0. Never gamma/delta.
"""
from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass

import numpy as np

MAGIC = b"RCL1"
FORMAT_VERSION = 2
HEADER = struct.Struct("<4sHBBHHHHI")
TRAILER = struct.Struct("<I")      # CRC-32 (zlib) of every byte before it
MAX_CELLS = 4096
AXES = ("torque_nm", "speed_rpm", "udc_v")
MAX_MAP_ID = 0xFFFFFFFF    # u32; 0 is what the drive reports when it holds no LUT


class LutImageError(ValueError):
    """The image is malformed or cannot be built (the drive answers SDO abort 0x08000020)."""


@dataclass(frozen=True)
class Lut:
    """A decoded image: map id, axes, theta per cell [udc][speed][torque] (0 where invalid), validity, CRC."""
    map_id: int
    harmonic_order: int
    torque_nm: np.ndarray      # (n_t,)
    speed_rpm: np.ndarray      # (n_n,)
    udc_v: np.ndarray          # (n_u,)
    theta_cos: np.ndarray      # (n_u, n_n, n_t), 0 where invalid
    theta_sin: np.ndarray
    valid: np.ndarray          # bool (n_u, n_n, n_t)
    crc: int                   # image_crc: CRC-32 of the image without its CRC field

    def theta(self, torque_nm: float, speed_rpm: float, udc_v: float) -> tuple[float, float]:
        """Multilinear interpolation of (theta_cos, theta_sin), clamped at the axis ends."""
        tc, ts = 0.0, 0.0
        for (iu, wu) in _weights(self.udc_v, udc_v):
            for (i_n, wn) in _weights(self.speed_rpm, speed_rpm):
                for (it, wt) in _weights(self.torque_nm, torque_nm):
                    w = wu * wn * wt
                    if w != 0.0:
                        tc += w * float(self.theta_cos[iu, i_n, it])
                        ts += w * float(self.theta_sin[iu, i_n, it])
        return tc, ts


def _weights(axis: np.ndarray, x: float) -> list[tuple[int, float]]:
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
    return _crc32(bytes(blob)[:-TRAILER.size])


def crc_hex(crc: int) -> str:
    """A CRC as the service shows it everywhere (API, CLI, dashboard): 0x and 8 upper-case hex digits."""
    return f"0x{int(crc):08X}"


def _crc32(body: bytes) -> int:
    return zlib.crc32(body) & 0xFFFFFFFF


def encode(harmonic_order: int, torque_nm, speed_rpm, udc_v, theta_cos, theta_sin, valid=None, *,
           map_id: int) -> bytes:
    """An image of map `map_id` from the axes and [udc][speed][torque] arrays (nested lists or arrays
    of that shape, or flat in that order). valid: 1/0 per cell (default all 1). Raises LutImageError
    if the map has more than MAX_CELLS cells, an axis is not strictly increasing or map_id is not in
    1 .. MAX_MAP_ID."""
    if not 1 <= int(map_id) <= MAX_MAP_ID:
        raise LutImageError(f"map_id {map_id} is not in 1 .. {MAX_MAP_ID} (0 means no LUT)")
    axes = (torque_nm, speed_rpm, udc_v)
    nt, nn, nu = (len(a) for a in axes)
    if nt * nn * nu > MAX_CELLS:
        raise LutImageError(f"map has {nt * nn * nu} cells; the drive takes at most {MAX_CELLS}")
    for name, axis in zip(AXES, axes):
        if any(b <= a for a, b in zip(axis, axis[1:])):
            raise LutImageError(f"axis {name} is not strictly increasing")
    shape = (nu, nn, nt)
    tc = np.asarray(theta_cos, dtype="<f4").reshape(shape)
    tsn = np.asarray(theta_sin, dtype="<f4").reshape(shape)
    v = np.ones(shape, dtype=np.uint8) if valid is None else np.asarray(valid, dtype=np.uint8).reshape(shape)
    body = HEADER.pack(MAGIC, FORMAT_VERSION, int(harmonic_order), 0, nt, nn, nu, 0, int(map_id))
    for axis in axes:
        body += np.asarray(axis, dtype="<f4").tobytes()
    body += tc.tobytes() + tsn.tobytes() + v.tobytes()
    return body + TRAILER.pack(_crc32(body))


def decode(blob: bytes) -> Lut:
    """Check and decode an image; LutImageError says what is wrong."""
    blob = bytes(blob)
    if len(blob) < 6:
        raise LutImageError(f"image too short ({len(blob)} bytes)")
    magic, version = struct.unpack_from("<4sH", blob, 0)
    if magic != MAGIC:
        raise LutImageError(f"bad magic {magic!r}")
    if version != FORMAT_VERSION:       # before the length: another version has another header
        raise LutImageError(f"unsupported format_version {version}: this drive takes version {FORMAT_VERSION} "
                            f"(its header carries the map id)")
    if len(blob) < HEADER.size + TRAILER.size:
        raise LutImageError(f"image too short ({len(blob)} bytes)")
    _magic, _version, h, _r0, nt, nn, nu, _r1, map_id = HEADER.unpack_from(blob, 0)
    if map_id == 0:
        raise LutImageError("map_id 0 is reserved (the drive reports 0 when it holds no LUT)")
    if h < 1:
        raise LutImageError("harmonic_order must be >= 1")
    if min(nt, nn, nu) < 1 or nt * nn * nu > MAX_CELLS:
        raise LutImageError(f"bad axis lengths {nt} x {nn} x {nu}")
    cells = nt * nn * nu
    expected = HEADER.size + 4 * (nt + nn + nu) + 8 * cells + cells + TRAILER.size
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
    tc = np.frombuffer(blob, dtype="<f4", count=cells, offset=off).astype(np.float64).reshape(nu, nn, nt)
    off += 4 * cells
    tsn = np.frombuffer(blob, dtype="<f4", count=cells, offset=off).astype(np.float64).reshape(nu, nn, nt)
    off += 4 * cells
    valid = np.frombuffer(blob, dtype=np.uint8, count=cells, offset=off).reshape(nu, nn, nt)
    if np.any(valid > 1):
        raise LutImageError("valid flags must be 0 or 1")
    if not (np.all(np.isfinite(tc)) and np.all(np.isfinite(tsn))):
        raise LutImageError("theta values not finite")
    ok = valid == 1
    return Lut(int(map_id), int(h), axes[0], axes[1], axes[2], np.where(ok, tc, 0.0), np.where(ok, tsn, 0.0), ok, crc)
