"""LUT download end to end: `ripplecal serve` with plant_emulator in its own process, maps stored as
finished sweeps store them. The rules (no ok cell: 422; holes: 409 unless force; a failed cell's fill goes
in unless fill=false), the CRC (CRC-32
of the image without its CRC field, so two maps give two CRCs), and the drive reporting which map it
holds (0x2001:4 and :2) in /bench/status, read back at the download and again by the status poller."""

from __future__ import annotations

import time

import httpx
import pytest

from drivers.lut_image import DEFAULT_INTERPOLATION, crc_hex, image_crc
from service.api.public.maps import map_public
from service.maps.lut_export import lut_image
from service.store.storage import Storage
from tests.support.service_process import ServiceProcess, create_token
from tests.support.stored_maps import CELLS, stored_map
from tests.support.waiting import wait_until

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    db = tmp_path_factory.mktemp("lut") / "ripplecal.db"
    storage = Storage(db)  # the maps exist before the service opens the database
    maps = {
        "full": stored_map(storage),
        "other": stored_map(storage, gamma_offset_deg=0.5),
        "partial": stored_map(storage, failing={CELLS[1]}),
        "empty": stored_map(storage, failing=set(CELLS)),
    }
    expected_crc = {
        name: crc_hex(image_crc(lut_image(map_public(storage, i).model_dump()))) for name, i in maps.items()
    }
    expected_crc["partial without fill"] = crc_hex(
        image_crc(lut_image(map_public(storage, maps["partial"]).model_dump(), fill=False))
    )
    token = create_token(db)
    svc = ServiceProcess(db)
    try:
        svc.wait_ready()
        with httpx.Client(base_url=svc.base + "/api/v1", timeout=30, headers={"Authorization": f"Bearer {token}"}) as c:
            yield c, maps, expected_crc
    finally:
        svc.stop()


def _lut_status(client) -> dict:
    return client.get("/bench/status").json()["lut"]


def test_download_rules_crc_and_the_map_the_drive_holds(bench):
    client, maps, expected_crc = bench
    assert _lut_status(client)["status"] == "none" and _lut_status(client)["map_id"] is None  # read at start

    r = client.post(f"/maps/{maps['empty']}/download")
    assert r.status_code == 422 and "no valid cell (0 of 4 ok)" in r.json()["detail"][0]["msg"], r.text
    # the failed cell lies between ok ones: it carries a fill; without the fill it would be a hole
    r = client.post(f"/maps/{maps['partial']}/download", params={"fill": "false"})
    assert r.status_code == 409 and "1 of 4 cells are not ok" in r.json()["detail"] and "force" in r.json()["detail"]
    assert _lut_status(client)["map_id"] is None  # nothing went to the drive
    r = client.post(f"/maps/{maps['partial']}/download", params={"force": "true", "fill": "false"})
    assert r.status_code == 200, r.text
    assert r.json() == {
        "map_id": maps["partial"],
        "crc32": expected_crc["partial without fill"],
        "bytes": 20 + 4 * 5 + 9 * 4 + 4,
        "cells": 4,
        "valid_cells": 3,
        "filled_cells": 0,
        "injection_off_cells": 0,
        "fill": False,
        "interpolation": DEFAULT_INTERPOLATION,
        "format_version": 3,
        "harmonic_order": 6,
        "orders": [6],  # a map of one order: its own
        "forced": True,
    }
    r = client.post(f"/maps/{maps['partial']}/download")  # with its fill (the default): no hole, no force
    assert r.status_code == 200, r.text
    assert (r.json()["crc32"], r.json()["filled_cells"], r.json()["forced"]) == (expected_crc["partial"], 1, False)
    lut = _lut_status(client)  # the drive's read-back at the download
    assert (lut["map_id"], lut["crc32"], lut["status"], lut["last_error"], lut["stale"]) == (
        maps["partial"],
        expected_crc["partial"],
        "in_force",
        None,
        False,
    )

    crcs = {}
    for name in ("full", "other"):
        r = client.post(f"/maps/{maps[name]}/download")  # complete maps need no force
        assert r.status_code == 200 and r.json()["forced"] is False, r.text
        crcs[name] = r.json()["crc32"]
        assert crcs[name] == expected_crc[name] and _lut_status(client)["map_id"] == maps[name]
    assert crcs["full"] != crcs["other"] and "0x2144DF1C" not in crcs.values()  # not the CRC-32 residue
    # the status poller reads the drive's own objects again while the bench is idle (1 Hz)
    downloaded_at = time.monotonic()
    lut = wait_until(
        lambda: time.monotonic() - downloaded_at > 2.5 and (s := _lut_status(client))["age_s"] < 1.5 and s,
        timeout_s=30,
        what="a fresh read of the drive's LUT objects",
    )
    assert (lut["map_id"], lut["crc32"], lut["status"]) == (maps["other"], crcs["other"], "in_force")
    assert client.post("/maps/987654/download").status_code == 404
