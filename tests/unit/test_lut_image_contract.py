"""The LUT image contract (drivers/lut_image.py): one encoder and one decoder, imported by the service's
builder (service/lut_export.py) and the emulated drive firmware; the image bytes after the header are
those the two separate implementations produced before they were merged into one codec; the CRC is
CRC-32 of the image without its CRC field, so two maps have two CRCs."""
from __future__ import annotations

import hashlib
import struct
import zlib

import numpy as np
import pytest

from drivers import lut_image
from service.lut_export import lut_image as service_image

AXES = {"torque_nm": [1.0, 2.5, 4.0], "speed_rpm": [1000.0, 2000.0], "udc_v": [12.0, 24.0]}
# sha256 of the 156-byte format_version 1 image of FIXED_MAP, recorded from service/lut_export.py at
# commit e535cf8 (its own struct-based builder, before the codec moved to drivers/lut_image.py)
IMAGE_SHA256_BEFORE = "13b598b43bd3a1b202d398b6f899d1a24e33ba6182beebdd231bc7e66ac8929f"
V1_HEADER = struct.Struct("<4sHBBHHHH")     # version 2 appended u32 map_id to it
RESIDUE = 0x2144DF1C                        # CRC-32 over any image including its own CRC: the old bug
MAP_ID = 7


def fixed_map() -> dict:
    """12 cells, theta_cos = 0.01 k, theta_sin = -0.003 k^2 (k = 1..12 in [udc][speed][torque] order),
    every 4th cell below target (not valid)."""
    cells, k = [], 0
    for u in AXES["udc_v"]:
        for n in AXES["speed_rpm"]:
            for t in AXES["torque_nm"]:
                k += 1
                cells.append({"torque_nm": t, "speed_rpm": n, "udc_v": u, "theta_cos": 0.01 * k,
                              "theta_sin": -0.003 * k * k, "status": "ok" if k % 4 else "below_target"})
    return {"id": MAP_ID, "harmonic_order": 6, "axes": AXES, "cells": cells}


def test_the_service_image_of_a_fixed_map_is_the_version_1_image_with_the_map_id_in_its_header():
    image = service_image(fixed_map())
    assert len(image) == 160
    magic, version, h, _, nt, nn, nu, _, map_id = lut_image.HEADER.unpack_from(image)
    assert (magic, version, h, nt, nn, nu, map_id) == (b"RCL1", 2, 6, 3, 2, 2, MAP_ID)
    # the same payload under the version 1 header (CRC made again) is byte for byte the image of e535cf8
    v1 = V1_HEADER.pack(b"RCL1", 1, 6, 0, 3, 2, 2, 0) + image[lut_image.HEADER.size:-4]
    v1 += struct.pack("<I", zlib.crc32(v1))
    assert hashlib.sha256(v1).hexdigest() == IMAGE_SHA256_BEFORE


def test_the_crc_is_crc32_of_the_image_without_its_crc_field():
    image = service_image(fixed_map())
    crc = lut_image.image_crc(image)
    assert crc == zlib.crc32(image[:-4]) == struct.unpack("<I", image[-4:])[0]   # the trailer holds it
    assert lut_image.decode(image).crc == crc != RESIDUE
    assert zlib.crc32(image) == RESIDUE        # what the drive reported for every map before
    assert lut_image.crc_hex(crc) == f"0x{crc:08X}"


def test_two_maps_have_two_crcs():
    other_values = fixed_map()
    other_values["cells"][0]["theta_cos"] += 1e-3
    crcs = {lut_image.image_crc(service_image(m)) for m in (fixed_map(), other_values, {**fixed_map(), "id": 8})}
    assert len(crcs) == 3      # another theta, or the same values under another map id


def test_decode_refuses_another_format_version_and_map_id_0():
    image = bytearray(service_image(fixed_map()))
    struct.pack_into("<H", image, 4, 1)
    with pytest.raises(lut_image.LutImageError, match="unsupported format_version 1: this drive takes version 2"):
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
    with pytest.raises(ValueError, match="axis torque_nm is not strictly increasing"):   # the API's 422
        service_image({**fixed_map(), "axes": {**AXES, "torque_nm": [1.0, 1.0, 4.0]}})
