"""Issue 11, point 4: raw recordings, end to end through the real emulator and the API.

Every identification (a job or a sweep point) keeps the DAQ samples it counted as plant time and
its theta setpoints in an MF4 file read back here with asammdf: samples = plant_time_s x sample
rate exactly (the DAQ lost none), the setpoints are the thetas of the result's history, each at the
sample where the drive's sync line toggled. Retention (a tiny keep_gb: only the newest file is kept)
deletes the oldest, and a recordings directory that cannot be used loses the recording, never the
result.
"""

import io
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from asammdf import MDF

from drivers.daq_protocol import FLAG_SYNC_INPUT
from service.store.recordings import DAQ_CHANNELS, SETPOINT_CHANNELS, header_properties
from tests.support.live_app import wait_finished
from tests.support.operating_points import OP1

pytestmark = pytest.mark.e2e
TINY_GB = 1e-9  # 1 byte: after each write every older recording goes (the newest is always kept)
LIVE_SETTINGS = {"recordings.keep_gb": TINY_GB}  # the module's `live` (tests/conftest.py)


def _identify(live, method: str, options: dict | None = None) -> dict:
    service, client, operator = live
    r = client.post(
        "/api/v1/identifications",
        json={"operating_point": OP1, "method": method, "options": options or {}},
        headers=operator,
    )
    assert r.status_code == 202, r.text
    job = wait_finished(client, f"/api/v1/jobs/{r.json()['id']}", timeout_s=300)
    assert job["state"] == "done", job
    return job["result"]


@pytest.fixture(scope="module")
def probe(live):
    return _identify(live, "probe")


def _download(client, result_id: int) -> MDF:
    r = client.get(f"/api/v1/results/{result_id}/recording", params={"format": "mf4"})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "application/octet-stream"
    assert r.headers["content-disposition"] == f'attachment; filename="ripplecal_result{result_id}.mf4"'
    return MDF(io.BytesIO(r.content))


def test_probe_recording_opens_in_asammdf_and_holds_the_plant_time(live, probe):
    service, client, _ = live
    rec = probe["recording"]
    assert rec["available"] and rec["error"] is None, rec
    rate = service.settings.daq.sample_rate_hz
    with _download(client, probe["id"]) as mdf:
        assert {ch for group in mdf.groups for ch in (c.name for c in group.channels)} >= {
            *DAQ_CHANNELS,
            *SETPOINT_CHANNELS,
        }
        alpha, angle = mdf.get("alpha"), mdf.get("angle")
        index = mdf.get("sample_index").samples
        flags = mdf.get("flags").samples
        assert (alpha.unit, angle.unit) == ("rad/s^2", "rad")
        # the samples are exactly the plant time: no DAQ sample was lost, so counting indices = counting samples
        assert not mdf.get("gap_before").samples.any()
        assert len(alpha) == rec["samples"] == round(probe["plant_time_s"] * rate)
        np.testing.assert_allclose(alpha.timestamps, index / rate, rtol=0, atol=1e-12)
        assert np.all(np.diff(index) > 0)
        full_scale = service.settings.daq.accel_full_scale_rad_s2
        assert 0 < np.max(np.abs(alpha.samples)) <= full_scale
        assert 0 <= np.min(angle.samples) and np.max(angle.samples) < 2 * np.pi

        # the setpoints are the thetas the result's history shows, in order
        tc, ts = mdf.get("theta_cos"), mdf.get("theta_sin")
        effect = mdf.get("effect_sample_index").samples
        assert mdf.get("theta_cos").unit == "rad" and len(tc) == rec["setpoints"]
        history = np.array(probe["traces"]["theta_history"])[:, 1:3]
        recorded = np.column_stack([tc.samples, ts.samples])
        for theta in history:
            assert np.min(np.hypot(*(recorded - theta).T)) < 1e-12, f"history theta {theta} not among the setpoints"
        np.testing.assert_allclose(tc.timestamps, effect / rate, rtol=0, atol=1e-12)
        gamma = mdf.get("gamma")
        np.testing.assert_allclose(gamma.samples, np.degrees(np.hypot(tc.samples, ts.samples)), atol=1e-9)
        # each setpoint's effect sample starts a segment of the recording, where the sync line toggled
        position = np.searchsorted(index, effect)
        assert np.array_equal(index[position], effect)
        sync = (flags & FLAG_SYNC_INPUT) != 0
        assert all(sync[p] != sync[p - 1] for p in position[1:])
        assert position[0] == 0

        # the header says what was measured where, by what
        props = header_properties(mdf.header.comment)
        assert (
            ET.fromstring(mdf.header.comment)
            .find("TX")
            .text.startswith(f"ripplecal raw recording of result {probe['id']}")
        )
        assert props["result_id"] == str(probe["id"]) and props["method"] == "probe"
        assert (float(props["torque_nm"]), float(props["speed_rpm"]), float(props["udc_v"])) == tuple(OP1.values())
        assert props["bench_identity"] == probe["bench_identity"]
        assert props["software_version"] == probe["software_version"]
        assert int(props["stale_samples"]) == rec["stale_samples"]


def test_recording_route_refuses_what_it_cannot_give(live, probe):
    _, client, _ = live
    r = client.get(f"/api/v1/results/{probe['id']}/recording", params={"format": "csv"})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "format"], r.text
    r = client.get("/api/v1/results/999999/recording")
    assert r.status_code == 404 and r.json()["detail"] == "result 999999 does not exist"


def test_every_sweep_point_is_recorded_and_retention_deletes_the_oldest(live, probe):
    service, client, operator = live
    r = client.post(
        "/api/v1/sweeps",
        headers=operator,
        json={
            "grid": {"torque_nm": [2.0, 2.5], "speed_rpm": [OP1["speed_rpm"]], "udc_v": [OP1["udc_v"]]},
            "method": "adaptive",
        },
    )
    assert r.status_code == 202, r.text
    sweep = wait_finished(client, f"/api/v1/sweeps/{r.json()['id']}", timeout_s=300)
    assert sweep["state"] == "done", sweep
    first, last = (p["result"] for p in sweep["points"])
    for point in (first, last):
        assert point["recording"]["samples"] == round(point["plant_time_s"] * service.settings.daq.sample_rate_hz)
    # keep_gb = 1e-9: each write left only itself; the probe's and the first point's recordings are gone
    assert last["recording"]["available"]
    with _download(client, last["id"]) as mdf:
        assert len(mdf.get("alpha")) == last["recording"]["samples"]
    for older in (probe["id"], first["id"]):
        rec = client.get(f"/api/v1/results/{older}").json()["recording"]
        assert not rec["available"] and "deleted by retention" in rec["error"], rec
        r = client.get(f"/api/v1/results/{older}/recording")
        assert r.status_code == 404 and "deleted by retention" in r.json()["detail"], r.text
    files = sorted(p.name for p in service.recordings.directory.iterdir())
    assert files == [f"result-{last['id']}.mf4"], files


def test_unusable_recordings_directory_loses_the_recording_not_the_result(live):
    service, client, _ = live
    directory = service.recordings.directory
    aside = directory.with_name("recordings-aside")
    directory.rename(aside)
    directory.write_text("a file where the recordings directory should be")
    try:
        result = _identify(
            live,
            "grid",
            {
                "gamma_start_deg": 2.0,
                "gamma_stop_deg": 4.0,
                "gamma_step_deg": 2.0,
                "delta_start_deg": 0.0,
                "delta_stop_deg": 180.0,
                "delta_step_deg": 180.0,
            },
        )
    finally:
        directory.unlink()
        aside.rename(directory)
    assert result["status"] != "failed" and result["theta_cos"] is not None, result
    assert client.get(f"/api/v1/results/{result['id']}").json()["status"] == result["status"]
    rec = result["recording"]
    assert not rec["available"] and "recordings directory is unusable" in rec["error"], rec
    assert str(directory) not in rec["error"], rec  # no server path in an answer
    r = client.get(f"/api/v1/results/{result['id']}/recording")
    assert r.status_code == 404 and "unusable" in r.json()["detail"], r.text
