"""The download rules of service/runs/lut_download.py under the fill choice, on a hand-built map (the refined
map of test_lut_readers: 27 ok cells, 2 filled, 1 hole): holes are the cells that would inject nothing
under the chosen fill; the image carries flag 2 only with fill; the receipt says what went in. No
bench: a stand-in drive decodes the image with the drive's own codec and reports it back."""

from __future__ import annotations

import pytest

from drivers import lut_image
from service.maps.view import MapView
from service.runs import lut_download
from tests.unit.test_lut_readers import FILLED, HOLE, MAP_ID, refined_map


class Drive:
    """Takes the image as the emulated drive does (drivers.lut_image.decode) and reports it."""

    def __init__(self):
        self.lut = None

    def download_lut(self, blob: bytes):
        from drivers.drive import LutInForce

        self.lut = lut_image.decode(blob)
        return LutInForce(map_id=self.lut.map_id, crc32=self.lut.crc, status="in_force")


@pytest.fixture
def serve_map(monkeypatch):
    """prepare() reads the map given here (MapView.model_dump() shape) instead of the database."""

    def serve(m: dict) -> None:
        monkeypatch.setattr(
            lut_download, "map_view", lambda storage, map_id: MapView(**m) if map_id == m["id"] else None
        )

    return serve


def _with(m: dict, point, **fields) -> dict:
    for c in m["cells"]:
        if (c["torque_nm"], c["speed_rpm"], c["udc_v"]) == point:
            c.update(fields)
    return m


def test_with_fill_only_the_cell_without_a_fill_is_a_hole(serve_map):
    serve_map(refined_map())
    with pytest.raises(
        lut_download.PartialMap, match=f"map {MAP_ID} is partial: 1 of 30 cells are not ok and carry no fill"
    ):
        lut_download.prepare(None, MAP_ID)
    lut = lut_download.prepare(None, MAP_ID, force=True)
    assert (lut.cells, lut.valid_cells, lut.filled_cells, lut.holes, lut.forced) == (30, 27, 2, 1, True)
    assert lut.receipt_fields() == {
        "filled_cells": 2,
        "injection_off_cells": 0,
        "fill": True,
        "interpolation": lut_image.DEFAULT_INTERPOLATION,
        "format_version": 3,
        "orders": [6],  # a map of one order: its own
    }
    decoded = lut_image.decode(lut.image)
    assert int((decoded.flags == 2).sum()) == 2 and int((decoded.flags == 0).sum()) == 1


def test_without_fill_the_filled_cells_are_holes_too(serve_map):
    serve_map(refined_map())
    with pytest.raises(
        lut_download.PartialMap, match="3 of 30 cells are not ok \\(2 of them filled, left out without fill\\)"
    ):
        lut_download.prepare(None, MAP_ID, fill=False)
    lut = lut_download.prepare(None, MAP_ID, force=True, fill=False)
    assert (lut.valid_cells, lut.filled_cells, lut.holes, lut.fill) == (27, 0, 3, False)
    assert int((lut_image.decode(lut.image).flags == 2).sum()) == 0


def test_a_map_whose_every_non_ok_cell_is_filled_needs_no_force_with_fill_only(serve_map):
    serve_map(
        _with(
            refined_map(),
            HOLE,
            status="below_target",
            theta_cos=0.01,
            theta_sin=-0.02,
            filled=True,
            fill_source="held from the nearest ok cell along torque_nm",
        )
    )
    lut = lut_download.prepare(None, MAP_ID)
    assert (lut.valid_cells, lut.filled_cells, lut.holes, lut.forced) == (27, 3, 0, False)
    with pytest.raises(lut_download.PartialMap):
        lut_download.prepare(None, MAP_ID, fill=False)


def test_a_map_without_an_ok_cell_is_refused_whatever_its_fills(serve_map):
    m = refined_map()
    for c in m["cells"]:
        if c["status"] == "ok":
            c.update(status="below_target", filled=True, fill_source="measured")
    serve_map(m)
    with pytest.raises(lut_download.LutRefused, match=f"map {MAP_ID} has no valid cell \\(0 of 30 ok\\)"):
        lut_download.prepare(None, MAP_ID, force=True)


def test_the_interpolation_goes_into_the_header_and_an_unknown_one_is_refused(serve_map):
    serve_map(refined_map())
    lut = lut_download.prepare(None, MAP_ID, force=True, interpolation="polar")
    assert lut.image[7] == 1 and lut_image.decode(lut.image).interpolation == "polar" and lut.interpolation == "polar"
    with pytest.raises(lut_download.LutRefused, match="interpolation 'spline' is not one of cartesian, polar"):
        lut_download.prepare(None, MAP_ID, force=True, interpolation="spline")
    with pytest.raises(lut_download.MapNotFound):
        lut_download.prepare(None, MAP_ID + 1)


def test_download_map_keeps_its_positional_signature_and_the_receipt_says_what_went_in(serve_map):
    serve_map(refined_map())
    drive = Drive()
    receipt = lut_download.download_map(None, drive, MAP_ID, True)  # as the API route and validation call it
    assert (receipt.map_id, receipt.cells, receipt.valid_cells, receipt.forced) == (MAP_ID, 30, 27, True)
    assert receipt.crc32 == lut_image.crc_hex(drive.lut.crc) and receipt.bytes == 24 + 4 * (3 + 5 + 2) + 9 * 30
    assert drive.lut.filled.sum() == len(FILLED)
    # the newer receipt fields, where lut_download.LutDownload has them (service/runs/lut_download.py)
    for key, value in {
        "filled_cells": 2,
        "injection_off_cells": 0,
        "fill": True,
        "interpolation": lut_image.DEFAULT_INTERPOLATION,
        "format_version": 3,
    }.items():
        if key in lut_download.LutDownload.model_fields:
            assert receipt.model_dump()[key] == value
    receipt = lut_download.download_map(None, drive, MAP_ID, force=True, fill=False, interpolation="polar")
    assert (drive.lut.interpolation, int(drive.lut.filled.sum())) == ("polar", 0)
