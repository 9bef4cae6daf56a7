"""Start `plant_emulator` as a child process and learn its endpoints from its first stdout line.

The child dies with the service, also when the service is killed with SIGKILL: it runs with
`--exit-on-stdin-eof` and its stdin is a pipe only this process holds, so the kernel closing that
pipe at our death (any death) stops it. It runs in its own session so that a terminal's Ctrl-C goes
to the service, which then stops it in order (bench safe first)."""

from __future__ import annotations

import json
import os
import selectors
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from typing import Any


class EmulatorError(RuntimeError):
    pass


@dataclass
class EmulatorProcess:
    scenario: str = "paper-bench"
    seed: int | None = None
    speedup: float = 0.0
    start_timeout_s: float = 60.0
    process: subprocess.Popen[str] | None = None  # text=True
    endpoints: dict[str, Any] | None = None

    def start(self) -> dict[str, Any]:
        cmd = [
            sys.executable,
            "-m",
            "plant_emulator",
            "--scenario",
            self.scenario,
            "--speedup",
            str(self.speedup),
            "--exit-on-stdin-eof",
        ]
        if self.seed is not None:
            cmd += ["--seed", str(self.seed)]
        self.process = subprocess.Popen(
            cmd,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=None,
            text=True,
            start_new_session=True,
            close_fds=True,
        )
        stdout = self.process.stdout
        assert stdout is not None  # stdout=PIPE
        sel = selectors.DefaultSelector()
        sel.register(stdout, selectors.EVENT_READ)
        deadline = time.monotonic() + self.start_timeout_s
        line = ""
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise EmulatorError(
                    f"plant_emulator exited with code {self.process.returncode} before naming its endpoints"
                )
            if sel.select(timeout=0.2):
                line = stdout.readline()
                break
        sel.close()
        if not line:
            self.stop()
            raise EmulatorError(f"plant_emulator named no endpoints within {self.start_timeout_s} s")
        try:
            self.endpoints = json.loads(line)
        except json.JSONDecodeError as exc:
            self.stop()
            raise EmulatorError(f"plant_emulator's first line is not JSON: {line[:200]!r} ({exc})") from None
        return self.endpoints

    def stop(self, timeout_s: float = 10.0) -> None:
        proc, self.process = self.process, None
        if proc is None:
            return
        if proc.stdin is not None:
            try:
                proc.stdin.write("stop\n")  # an orderly stop, said (plant_emulator/process.py STOP_LINE) ...
                proc.stdin.flush()
            except OSError:
                pass
            try:
                proc.stdin.close()  # ... then the child's cue, should the signal not reach it
            except OSError:
                pass
        if proc.poll() is not None:
            return
        try:
            os.killpg(proc.pid, signal.SIGTERM)
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=timeout_s)
