"""A second python-can interface end to end (issue 29): the service on python-can's own `slcan` interface (the
Lawicel ASCII protocol of many USB-CAN adapters), here over pyserial's socket:// to the emulator's slcan adapter on
the same bus as its socketcand server. One emulated bench, two services after one another (each leaves the drive
safe and its heartbeat consumers disarmed, so the next needs no fault reset): over socketcand, then over slcan.
An identification and a sweep give the same theta over both within what their 40 dB allows (at 40 dB the residual
is 1 % of the harmonic: each theta within ~1 % of theta*, the test allows 5 %); the sweep's LUT download and a
validation run over slcan."""

from __future__ import annotations

import math

import pytest

from tests.support.bench_rig import Api, EmulatorRig
from tests.support.service_process import ServiceProcess

pytestmark = pytest.mark.e2e
OP = {"torque_nm": 2.5, "speed_rpm": 1400, "udc_v": 12}
GRID = {"torque_nm": [2.0, 3.0], "speed_rpm": [1200, 1600], "udc_v": [12]}


def _served(emu: EmulatorRig, directory, transport: str) -> tuple[ServiceProcess, Api]:
    db = directory / f"{transport}.db"
    svc = ServiceProcess(db, "--bench", str(emu.bench_file(directory, name=f"bench-{transport}", transport=transport)))
    svc.wait_ready()
    return svc, Api(svc, db)


def test_slcan_runs_the_bench_as_socketcand_does(tmp_path):
    emu = EmulatorRig()
    try:
        results, maps = {}, {}
        for transport in ("socketcand", "slcan"):
            svc, api = _served(emu, tmp_path, transport)
            try:
                job = api.identify(OP, "probe")
                assert job["state"] == "done" and job["result"]["status"] == "ok", job
                results[transport] = job["result"]
                r = api.post("/sweeps", {"grid": GRID, "method": "probe"})
                assert r.status_code == 202, r.text
                sweep = api.sweep_finished(r.json()["id"], 300)
                assert sweep["state"] == "done" and sweep["map_id"] is not None, sweep
                assert sweep["progress"]["ok"] >= 3, sweep["progress"]
                maps[transport] = api.get(f"/maps/{sweep['map_id']}")
                if transport == "slcan":
                    r = api.post(f"/maps/{sweep['map_id']}/validate", {"force": True})
                    assert r.status_code == 202, r.text
                    job = api.job_finished(r.json()["id"], 300)
                    v = job["validation"]
                    assert job["state"] == "done" and v["download"]["crc32"].startswith("0x"), job
                    assert sum(c["status"] == "measured" for c in v["cells"]) == 9, v["cells"]
                    # the LUT went in over slcan and the drive reports it back
                    assert api.get("/bench/status")["lut"]["map_id"] == sweep["map_id"]
            finally:
                api.close()
                svc.stop()
        a, b = (complex(results[t]["theta_cos"], results[t]["theta_sin"]) for t in ("socketcand", "slcan"))
        assert abs(a - b) <= 0.05 * abs(a), (a, b, math.degrees(abs(a - b)))
        # the sweep too: every cell ok over both transports lands on the same theta
        compared = 0
        for x, y in zip(maps["socketcand"]["cells"], maps["slcan"]["cells"]):
            assert (x["torque_nm"], x["speed_rpm"]) == (y["torque_nm"], y["speed_rpm"])
            if x["status"] == y["status"] == "ok":
                ta, tb = complex(x["theta_cos"], x["theta_sin"]), complex(y["theta_cos"], y["theta_sin"])
                assert abs(ta - tb) <= 0.05 * abs(ta), (x, y)
                compared += 1
        assert compared >= 3, (maps["socketcand"]["cells"], maps["slcan"]["cells"])
        faults = emu.control({"status": True})["faults"]
        assert faults["drive_injection_mode"] == 0 and faults["drive_torque_nm"] == 0.0, faults
    finally:
        emu.stop()
