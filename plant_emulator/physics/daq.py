"""The DAQ side of the emulator: accelerometer counts and the 12-byte frames on the wire.

The frame layout is not written here: sync bytes, field offsets, CRC table and CRC step, flag bits and
the count scales come from drivers/daq_protocol.py (docs/interfaces.md, "DAQ stream frame"), the module the service's
reader decodes with; numba compiles them in as constants, and `write_frame` jits
`daq_protocol.crc16_step` itself. Counts: alpha_meas / full scale * 32767, clipped to +-32767
(over-range flag), rounded half away from zero; angle phi_e * 65536 / (2 pi) rounded, modulo 65536.
"""

from __future__ import annotations

import math

from numba import njit

from drivers import daq_protocol as wire

# ---- parameters (indices into p) ----
P_ALPHA_FS = 22  # rad/s^2, sensor full scale (+-32767 counts)

# ---- setpoints (indices into sp) ----
S_SYNC = 9  # 0/1, level of the DAQ sync flag during this call

FRAME_BYTES = wire.FRAME_BYTES
SYNC_FLAG = wire.FLAG_SYNC_INPUT
OVER_RANGE_FLAG = wire.FLAG_OVER_RANGE
ACCEL_FS_COUNTS = float(wire.ACCEL_FULL_SCALE_COUNTS)
COUNTS_PER_RAD = wire.ANGLE_COUNTS_PER_TURN / (2.0 * math.pi)
SYNC_0 = wire.SYNC_0
SYNC_1 = wire.SYNC_1
OFFSET_SEQ = wire.OFFSET_SEQ
OFFSET_ANGLE = wire.OFFSET_ANGLE
OFFSET_ACCEL = wire.OFFSET_ACCEL
OFFSET_FLAGS = wire.OFFSET_FLAGS
OFFSET_CRC = wire.OFFSET_CRC
CRC_FIRST = wire.CRC_FIRST
CRC_STOP = wire.CRC_STOP
CRC_INIT = wire.CRC_INIT

crc16_step = njit(cache=True, inline="always")(wire.crc16_step)
# write_frame feeds the CRC from the field values, so the span must be exactly these fields in order
assert (CRC_FIRST, CRC_STOP) == (OFFSET_SEQ, OFFSET_FLAGS + 2)
assert OFFSET_ANGLE == OFFSET_SEQ + 2 and OFFSET_ACCEL == OFFSET_ANGLE + 2 and OFFSET_FLAGS == OFFSET_ACCEL + 2


@njit(cache=True, inline="always")
def accel_counts(a_meas, full_scale):
    """(counts as float, over range?) of a measured acceleration (rad/s^2) on the +-32767 scale."""
    raw = a_meas / full_scale * ACCEL_FS_COUNTS
    over = False
    if raw > ACCEL_FS_COUNTS:
        raw = ACCEL_FS_COUNTS
        over = True
    elif raw < -ACCEL_FS_COUNTS:
        raw = -ACCEL_FS_COUNTS
        over = True
    return raw, over


@njit(cache=True, inline="always")
def _put_u16(frames, at, value):
    frames[at] = value & 0xFF
    frames[at + 1] = value >> 8


@njit(cache=True, inline="always")
def write_frame(frames, o, seq, phi, raw, flags):
    """Frame of one sample at frames[o:o + FRAME_BYTES]: sequence number seq (mod 65536), angle phi_e
    (rad, [0, 2 pi)), acceleration counts raw (already clipped), status flags; CRC over the bytes
    [CRC_FIRST, CRC_STOP) as written."""
    # round half away from zero (int16 counts), angle counts modulo 65536
    acc = (int(raw + 0.5) if raw >= 0.0 else -int(-raw + 0.5)) & 0xFFFF
    ang = int(phi * COUNTS_PER_RAD + 0.5) & 0xFFFF
    sq = seq & 0xFFFF
    fl = flags & 0xFFFF
    frames[o] = SYNC_0
    frames[o + 1] = SYNC_1
    _put_u16(frames, o + OFFSET_SEQ, sq)
    _put_u16(frames, o + OFFSET_ANGLE, ang)
    _put_u16(frames, o + OFFSET_ACCEL, acc)
    _put_u16(frames, o + OFFSET_FLAGS, fl)
    # the CRC span holds these four fields in this order (checked at import), low byte first
    crc = crc16_step(CRC_INIT, sq & 0xFF)
    crc = crc16_step(crc, sq >> 8)
    crc = crc16_step(crc, ang & 0xFF)
    crc = crc16_step(crc, ang >> 8)
    crc = crc16_step(crc, acc & 0xFF)
    crc = crc16_step(crc, acc >> 8)
    crc = crc16_step(crc, fl & 0xFF)
    crc = crc16_step(crc, fl >> 8)
    _put_u16(frames, o + OFFSET_CRC, crc)
