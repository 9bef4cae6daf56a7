"""CAN transports side by side (issue 29): python-can's socketcand and slcan interfaces on the same emulated bench.

Run: python -m tests.benchmarks.bench_can_transports [--speedup 1] [--points 3]

Per transport: the SDO round trip (an expedited upload of 0x1000 from the drive, 200 times: median and p95, ms) and
the bench time of an identification (probe at 2.5 Nm / 1400 rpm / 12 V, through `ripplecal serve --bench`, the job's
started to finished, s; median of --points runs) at the emulator's speedup (1: a real bench's clock).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from datetime import datetime
from pathlib import Path

import canopen

from drivers import DRIVE_EDS
from tests.support.bench_rig import Api, EmulatorRig
from tests.support.service_process import ServiceProcess

OP = {"torque_nm": 2.5, "speed_rpm": 1400, "udc_v": 12}


def sdo_round_trip_ms(emu: EmulatorRig, transport: str, n: int = 200) -> list[float]:
    if transport == "slcan":
        kwargs = {"interface": "slcan", "channel": emu.endpoints["slcan"]["channel"], "sleep_after_open": 0}
    else:
        can = emu.endpoints["can"]
        kwargs = {"interface": "socketcand", "channel": can["channel"], "host": can["host"], "port": can["port"]}
    net = canopen.Network()
    net.connect(**kwargs)
    try:
        node = canopen.RemoteNode(emu.endpoints["drive_node"], str(DRIVE_EDS))
        net.add_node(node)
        out = []
        for _ in range(n):
            t0 = time.perf_counter()
            node.sdo.upload(0x1000, 0)
            out.append(1000.0 * (time.perf_counter() - t0))
        return out
    finally:
        net.disconnect()


def point_s(emu: EmulatorRig, transport: str, directory: Path, points: int) -> list[float]:
    db = directory / f"{transport}.db"
    svc = ServiceProcess(db, "--bench", str(emu.bench_file(directory, name=f"bench-{transport}", transport=transport)))
    svc.wait_ready()
    api = Api(svc, db)
    try:
        out = []
        for _ in range(points):
            job = api.identify(OP, "probe")
            assert job["state"] == "done", job
            out.append(
                (datetime.fromisoformat(job["finished_at"]) - datetime.fromisoformat(job["started_at"])).total_seconds()
            )
        return out
    finally:
        api.close()
        svc.stop()


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--speedup", type=float, default=1.0)
    parser.add_argument("--points", type=int, default=3)
    args = parser.parse_args()
    emu = EmulatorRig(speedup=args.speedup)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for transport in ("socketcand", "slcan"):
                rtt = sdo_round_trip_ms(emu, transport)
                wall = point_s(emu, transport, Path(tmp), args.points)
                print(
                    f"{transport:10s}: SDO round trip median {statistics.median(rtt):.2f} ms, "
                    f"p95 {sorted(rtt)[int(0.95 * len(rtt))]:.2f} ms; identification at 2.5 Nm / 1400 rpm (probe, "
                    f"speedup {args.speedup:g}): median {statistics.median(wall):.2f} s over {len(wall)} runs",
                    flush=True,
                )
    finally:
        emu.stop()


if __name__ == "__main__":
    main()
