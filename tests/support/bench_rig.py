"""An emulated bench in its own process, and the service pointed at it with `--bench` as at a real
bench (the interlock and crash end-to-end tests and tests/benchmarks/bench_faults.py). Faults go through the
emulator's control socket; the service never uses that socket."""

from __future__ import annotations

import contextlib
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Iterator

import httpx

from tests.support.service_process import REPO, ServiceProcess, create_token
from tests.support.waiting import wait_run_finished, wait_until


def emulator_control(endpoints: dict, command: dict, timeout_s: float = 10.0) -> dict:
    """One command to the emulator's fault-injection socket (test-only; the service never uses it), its
    JSON reply. endpoints: what the emulator printed at start (`EmulatorRig.endpoints`, or the endpoints
    of the emulator child a CalibrationService started)."""
    host, port = endpoints["control"].removeprefix("tcp://").rsplit(":", 1)
    with socket.create_connection((host, int(port)), timeout=timeout_s) as sock:
        sock.sendall((json.dumps(command) + "\n").encode())
        with sock.makefile() as lines:
            reply = lines.readline()
    if not reply.endswith("\n"):
        raise ConnectionError(f"the emulator's control socket closed before its reply to {command}: {reply!r}")
    return json.loads(reply)


class EmulatorRig:
    """`python -m plant_emulator` as its own process (stdin pipe held here: it dies with the test)."""

    def __init__(self, speedup: float = 0.0, timeout_s: float = 120.0, args: tuple[str, ...] = ()):
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "plant_emulator", "--speedup", str(speedup), "--exit-on-stdin-eof", *args],
            cwd=REPO,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        deadline = time.monotonic() + timeout_s
        line = ""
        while time.monotonic() < deadline and not line:
            line = self.proc.stdout.readline()
            if self.proc.poll() is not None:
                raise RuntimeError(f"plant_emulator exited with {self.proc.returncode}")
        self.endpoints = json.loads(line)

    def control(self, command: dict, timeout_s: float = 10.0) -> dict:
        return emulator_control(self.endpoints, command, timeout_s)

    def bench_file(self, directory: Path, name: str = "emulated-bench", transport: str = "socketcand") -> Path:
        """A bench file for the emulated bench; `transport` socketcand (its socketcand server) or slcan (the same
        bus as an slcan adapter on socket://, opened by python-can's own slcan interface)."""
        ep, can = self.endpoints, self.endpoints["can"]
        if transport == "slcan":
            link = f'[can]\ninterface = "slcan"\nchannel = "{ep["slcan"]["channel"]}"\nbitrate = 500000\n'
            options = "[can.options]\nsleep_after_open = 0\n"
        else:
            link = (
                f'[can]\ninterface = "{can["interface"]}"\nchannel = "{can["channel"]}"\nhost = "{can["host"]}"\n'
                f'port = {can["port"]}\n'
            )
            options = ""
        path = directory / f"{name}.toml"
        path.write_text(
            f'bench_name = "{name}"\n'
            f'{link}drive_node = {ep["drive_node"]}\nload_node = {ep["load_node"]}\n{options}'
            f'[daq]\nurl = "{ep["daq"]}"\nsample_rate_hz = {ep["sample_rate_hz"]}\n'
            f'[supply]\nurl = "{ep["supply"]}"\n'
        )
        return path

    def stop(self) -> None:
        """An orderly stop, said first (plant_emulator/process.py STOP_LINE: no warning of a parent gone)."""
        if self.proc.poll() is None:
            try:
                self.proc.stdin.write("stop\n")
                self.proc.stdin.flush()
            except (BrokenPipeError, OSError):
                pass
            self.proc.stdin.close()
            self.proc.terminate()
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)


class Api:
    """HTTP client of a running service with an operator token."""

    def __init__(self, service: ServiceProcess, db: Path):
        self.service = service
        self.token = create_token(db)
        self.http = httpx.Client(
            base_url=service.base + "/api/v1", timeout=30, headers={"Authorization": f"Bearer {self.token}"}
        )

    def get(self, path: str) -> dict:
        r = self.http.get(path)
        r.raise_for_status()
        return r.json()

    def post(self, path: str, body: dict | None = None) -> httpx.Response:
        return self.http.post(path, json=body)

    def wait(self, predicate, timeout_s: float = 180.0, what: str = "condition"):
        return wait_until(predicate, timeout_s, what, poll_s=0.1)

    def job_finished(self, job_id: int, timeout_s: float = 180.0) -> dict:
        return wait_run_finished(lambda: self.get(f"/jobs/{job_id}"), timeout_s, f"job {job_id}")

    def sweep_finished(self, sweep_id: int, timeout_s: float = 180.0) -> dict:
        return wait_run_finished(lambda: self.get(f"/sweeps/{sweep_id}"), timeout_s, f"sweep {sweep_id}")

    def identify(self, op: dict, method: str = "probe", timeout_s: float = 180.0) -> dict:
        r = self.post("/identifications", {"operating_point": op, "method": method})
        assert r.status_code == 202, r.text
        return self.job_finished(r.json()["id"], timeout_s)

    def close(self) -> None:
        self.http.close()


@contextlib.contextmanager
def served_bench(
    directory: Path,
    db_name: str,
    speedup: float = 0.0,
    transport: str = "socketcand",
    emulator_args: tuple[str, ...] = (),
) -> Iterator[tuple[EmulatorRig, ServiceProcess, "Api", Path]]:
    """An emulated bench and `ripplecal serve --bench` pointed at it, ready: (emulator, service, api, db);
    both processes stopped on the way out. speedup > 0: the emulator paced (see EmulatorRig); transport: the CAN
    interface the service opens (EmulatorRig.bench_file); emulator_args: e.g. ("--scenario", path)."""
    emu = EmulatorRig(speedup=speedup, args=emulator_args)
    db = directory / db_name
    svc = ServiceProcess(db, "--bench", str(emu.bench_file(directory, transport=transport)))
    try:
        svc.wait_ready()
        api = Api(svc, db)
        yield emu, svc, api, db
        api.close()
    finally:
        svc.stop()
        emu.stop()


def children_of(pid: int) -> list[int]:
    """Pids whose parent is `pid` (from /proc)."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.append(int(entry))
    return found


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False
