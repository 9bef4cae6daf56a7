"""The object dictionaries (drivers/eds/*.eds) are complete per CiA 306: eds-validate (eds-utils)
reports nothing on either file, canopen (the master's and the emulator's LocalNode's loader) reads
them, and [DeviceInfo] names the same device as the identity object 0x1018."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import canopen
import pytest

from drivers import DRIVE_EDS, LOAD_EDS

EDS_VALIDATE = Path(sys.executable).parent / "eds-validate"  # installed with the [test] extras


@pytest.mark.parametrize("eds", [DRIVE_EDS, LOAD_EDS], ids=lambda p: p.name)
def test_eds_validate_reports_nothing(eds):
    assert EDS_VALIDATE.exists(), f"{EDS_VALIDATE} missing: pip install -e '.[test]' (eds-utils)"
    before = eds.read_bytes()
    run = subprocess.run([str(EDS_VALIDATE), str(eds)], capture_output=True, text=True, timeout=60)
    assert (run.returncode, run.stdout, run.stderr) == (0, "", ""), run.stdout + run.stderr
    assert eds.read_bytes() == before  # a validator, not a fixer


@pytest.mark.parametrize("eds,product", [(DRIVE_EDS, 0x402), (LOAD_EDS, 0x403)], ids=["drive.eds", "load.eds"])
def test_canopen_loads_it_and_device_info_matches_the_identity_object(eds, product):
    od = canopen.import_od(str(eds), 5)
    info = od.device_information
    assert (
        (info.vendor_number, info.product_number, info.revision_number)
        == (od[0x1018][1].default, od[0x1018][2].default, od[0x1018][3].default)
        == (0xEAC, product, 0x00010000)
    )
    assert 1_000_000 in info.allowed_baudrates and 500_000 in info.allowed_baudrates
    assert info.product_name and info.order_code


def test_drive_eds_has_the_lut_map_id():
    od = canopen.import_od(str(DRIVE_EDS), 5)
    lut = od[0x2001]
    assert (
        lut[0].default == 4 and lut[4].name == "LUT map id" and lut[4].data_type == canopen.objectdictionary.UNSIGNED32
    )
    assert lut[4].access_type == "ro"
