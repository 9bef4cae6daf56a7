"""The LUT image contract (drivers/lut_image.py): one encoder and one decoder, imported by the service's
builder (service/lut_export.py) and the emulated drive firmware; the image bytes are those the two
separate implementations produced before they were merged into one codec."""
from __future__ import annotations

import hashlib
import zlib

import numpy as np
import pytest

from drivers import lut_image
from service.lut_export import lut_image as service_image

AXES = {"torque_nm": [1.0, 2.5, 4.0], "speed_rpm": [1000.0, 2000.0], "udc_v": [12.0, 24.0]}
# sha256 of the 156-byte image of FIXED_MAP, recorded from service/lut_export.py at commit e535cf8
# (its own struct-based builder, before the codec moved to drivers/lut_image.py)
IMAGE_SHA256_BEFORE = "13b598b43bd3a1b202d398b6f899d1a24e33ba6182beebdd231bc7e66ac8929f"


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
    return {"harmonic_order": 6, "axes": AXES, "cells": cells}


def test_the_service_image_of_a_fixed_map_is_byte_for_byte_what_it_was():
    image = service_image(fixed_map())
    assert len(image) == 156
    assert hashlib.sha256(image).hexdigest() == IMAGE_SHA256_BEFORE


def test_decode_inverts_encode_at_float32():
    k = np.arange(1, 13, dtype=float)
    valid = (k % 4 != 0).astype(int)
    tc, ts = np.where(valid == 1, 0.01 * k, 0.0), np.where(valid == 1, -0.003 * k * k, 0.0)
    image = lut_image.encode(6, AXES["torque_nm"], AXES["speed_rpm"], AXES["udc_v"], tc, ts, valid)
    assert image == service_image(fixed_map())
    lut = lut_image.decode(image)
    assert lut.harmonic_order == 6 and lut.crc == zlib.crc32(image)
    np.testing.assert_array_equal(lut.udc_v, AXES["udc_v"])
    np.testing.assert_array_equal(lut.valid.ravel(), valid == 1)
    np.testing.assert_array_equal(lut.theta_cos.ravel(), tc.astype(np.float32))
    np.testing.assert_array_equal(lut.theta_sin.ravel(), ts.astype(np.float32))


def test_encode_refuses_what_the_drive_would_refuse():
    with pytest.raises(lut_image.LutImageError, match="axis speed_rpm is not strictly increasing"):
        lut_image.encode(6, [1.0], [2000.0, 1000.0], [12.0], [0.0, 0.0], [0.0, 0.0])
    with pytest.raises(lut_image.LutImageError, match="map has 4097 cells; the drive takes at most 4096"):
        lut_image.encode(6, np.arange(4097.0), [1000.0], [12.0], np.zeros(4097), np.zeros(4097))
    with pytest.raises(ValueError, match="axis torque_nm is not strictly increasing"):   # the API's 422
        service_image({**fixed_map(), "axes": {**AXES, "torque_nm": [1.0, 1.0, 4.0]}})
