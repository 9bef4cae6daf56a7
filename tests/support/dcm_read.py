"""A DCM export read by dcmReader (the open-source reader of INCA / CANape's DCM 2.0), with no warning of its own."""

from __future__ import annotations

import logging
from pathlib import Path


def read_dcm(tmp_path: Path, text: str, caplog) -> dict:
    """{name: characteristic map} of the DCM `text` as dcmReader reads it; fails on any warning the reader logs."""
    from dcmReader.dcm_reader import DcmReader

    path = tmp_path / "lut.dcm"
    path.write_text(text)
    reader = DcmReader()
    with caplog.at_level(logging.WARNING, logger="dcmReader"):
        reader.read(str(path))
    assert not [r for r in caplog.records if r.name.startswith("dcmReader")], caplog.text
    return {k.name: k for k in reader.get_characteristic_maps()}
