"""Drive firmware (in process, no CAN): LUT download, CRC and map id read-back, refusal of bad images,
LUT-mode injection = interpolated theta, the eq. 11 switch 0x2000:8."""
from __future__ import annotations

import math
import struct
import zlib

import canopen
import numpy as np
import pytest

from drivers import DRIVE_EDS
from drivers import lut_image
from drivers.cia402 import State402
from plant_emulator import physics as ph
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


def image(scale=1.0, valid=None, h=6, map_id=3):
    tc = scale * np.arange(6, dtype=float).reshape(1, 2, 3) * 0.01
    ts = -scale * np.arange(6, dtype=float)[::-1].reshape(1, 2, 3) * 0.005
    return lut_image.encode(h, T_AX, N_AX, U_AX, tc, ts, valid, map_id=map_id), tc, ts


def with_repeated_torque_value(blob: bytes) -> bytes:
    """The image with its second torque axis value set to the first (CRC made valid again): the
    encoder refuses such an axis, so the refusal of the drive is tested on bytes patched by hand."""
    body = bytearray(blob[:-4])
    first = struct.unpack_from("<f", body, lut_image.HEADER.size)[0]
    struct.pack_into("<f", body, lut_image.HEADER.size + 4, first)
    return bytes(body) + struct.pack("<I", zlib.crc32(body))


def test_download_crc_read_back_and_refusal_keeps_old_lut(drive):
    assert [read(drive, 0x2001, sub) for sub in (2, 3, 4)] == [0, 0, 0]      # no LUT yet
    good, _, _ = image(map_id=41)
    write(drive, 0x2001, 1, good)
    assert read(drive, 0x2001, 2) == zlib.crc32(good[:-4]) == lut_image.image_crc(good)
    assert read(drive, 0x2001, 3) == 1
    assert read(drive, 0x2001, 4) == 41
    for bad in (good[:-1] + bytes([good[-1] ^ 1]),                     # CRC
                b"XCL1" + good[4:],                                     # magic
                good[:40],                                              # length
                with_repeated_torque_value(good),                       # axis
                good[:4] + b"\x01\x00" + good[6:]):                      # format version 1
        with pytest.raises(canopen.SdoAbortedError) as exc:
            write(drive, 0x2001, 1, bad)
        assert exc.value.code == 0x08000020
        assert read(drive, 0x2001, 2) == lut_image.image_crc(good)      # the old LUT stays in force
        assert read(drive, 0x2001, 4) == 41
        assert read(drive, 0x2001, 3) == 2
    assert drive.lut is not None and drive.lut.crc == lut_image.image_crc(good)
    other, _, _ = image(scale=2.0, map_id=42)                           # another map: another CRC
    write(drive, 0x2001, 1, other)
    assert read(drive, 0x2001, 4) == 42 and read(drive, 0x2001, 2) == lut_image.image_crc(other) != lut_image.image_crc(good)


def test_lut_mode_injects_the_interpolated_theta(drive):
    blob, tc, ts = image()
    write(drive, 0x2001, 1, blob)
    write(drive, 0x2000, 2, 2)                 # mode LUT
    write(drive, 0x6071, 0, 500)               # 2.5 Nm
    sp = ph.new_setpoints()
    while drive.chunk_setpoints(sp, 12.0):
        pass
    drive.speed_rpm = 2000.0                   # a grid point
    drive.chunk_setpoints(sp, 12.0)
    assert (sp[ph.S_THETA_COS], sp[ph.S_THETA_SIN]) == pytest.approx((tc[0, 1, 1], ts[0, 1, 1]), abs=1e-7)
    drive.speed_rpm = 1500.0                   # between points: bilinear in (torque, speed)
    drive.torque_nm = 3.25
    drive.chunk_setpoints(sp, 12.0)
    exp_c = 0.25 * (tc[0, 0, 1] + tc[0, 0, 2] + tc[0, 1, 1] + tc[0, 1, 2])
    exp_s = 0.25 * (ts[0, 0, 1] + ts[0, 0, 2] + ts[0, 1, 1] + ts[0, 1, 2])
    assert (sp[ph.S_THETA_COS], sp[ph.S_THETA_SIN]) == pytest.approx((exp_c, exp_s), abs=1e-7)
    drive.speed_rpm = 9000.0                   # clamped at the axis end
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
    assert sp[ph.S_H] == 12.0                  # the LUT's order
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
