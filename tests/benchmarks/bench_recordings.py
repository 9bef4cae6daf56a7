"""Raw recording figures on the emulated bench (run: python -m tests.benchmarks.bench_recordings).

Starts the service layer with plant_emulator (paper-bench, fast mode) and, at OP1 {2.5 Nm, 2000 rpm,
12 V}, runs probe, adaptive and grid (the paper's 360 points) identifications with recordings on
and off, alternating, and prints:
- bytes per plant second of the MF4 files (file size / plant_time_s), and per sample;
- the time the recording costs: making the recorder and inside it during the run
  (RecordingStore.recorder, RunRecorder.samples and .setpoint, timed around the calls) and the write after it (RecordingStore.keep: MF4 with transposed
  deflate, header, retention), against the identification's wall time;
- the median wall time per method with recordings on and off (the emulator's wall time varies from
  run to run, and much more on a loaded machine: the timed figures above are the direct measure,
  this is only a cross-check).
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

from service.api.public.results import result_public
from service.calibration_service import CalibrationService
from service.model.operating_point import OperatingPoint
from service.runs.identify import parse_options
from service.settings import load_settings
from service.store.recordings import RecordingStore, RunRecorder

OP1 = OperatingPoint(torque_nm=2.5, speed_rpm=2000, udc_v=12)
RUNS = {"probe": 5, "adaptive": 5, "grid": 1}


class Timed:
    """Seconds spent in the wrapped methods since the last reset."""

    def __init__(self):
        self.seconds = 0.0

    def wrap(self, cls, name: str) -> None:
        original = getattr(cls, name)

        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                self.seconds += time.perf_counter() - t0

        setattr(cls, name, timed)


def run_job(svc, method):
    t0 = time.perf_counter()
    job_id = svc.engine.submit_identification(OP1, method, parse_options(method, {}))
    deadline = time.monotonic() + 900
    while (job := svc.storage.get_job(job_id))["state"] not in ("done", "failed"):
        if time.monotonic() > deadline:
            raise TimeoutError(f"job {job_id} still {job['state']}")
        time.sleep(0.02)
    wall = time.perf_counter() - t0
    return result_public(svc.storage.get_result(job["result_id"])).model_dump(), wall


def main() -> None:
    db = Path(tempfile.mkdtemp()) / "bench.db"
    settings = load_settings(environ={}, overrides={"emulator.speedup": 0.0, "server.db_path": str(db)})
    in_run, writing = Timed(), Timed()
    in_run.wrap(RecordingStore, "recorder")  # the recorder made before the run (its MDF, temporary file)
    in_run.wrap(RunRecorder, "samples")
    in_run.wrap(RunRecorder, "setpoint")
    writing.wrap(RecordingStore, "keep")
    with CalibrationService(settings) as svc:
        rate = svc.settings.daq.sample_rate_hz
        print(f"recordings in {svc.recordings.directory}, {rate:g} samples/s")
        for method, runs in RUNS.items():
            walls = {True: [], False: []}
            per_plant_s, per_sample, in_run_share, write_share, write_s = [], [], [], [], []
            for i in range(2 * runs):
                on = i % 2 == 0
                svc.recordings.enabled = on
                in_run.seconds = writing.seconds = 0.0
                result, wall = run_job(svc, method)
                walls[on].append(wall)
                if on:
                    rec = result["recording"]
                    assert rec["available"], rec
                    per_plant_s.append(rec["bytes"] / result["plant_time_s"])
                    per_sample.append(rec["bytes"] / rec["samples"])
                    in_run_share.append(in_run.seconds / wall)
                    write_share.append(writing.seconds / wall)
                    write_s.append(writing.seconds)
                    plant = result["plant_time_s"]
            on_s, off_s = statistics.median(walls[True]), statistics.median(walls[False])
            print(
                f"{method} ({runs} runs each, last plant time {plant:.3f} s): "
                f"{statistics.median(per_plant_s) / 1e3:.1f} kB per plant second "
                f"({statistics.median(per_sample):.2f} B per sample, 23 B before compression); "
                f"recorder during the run {100 * statistics.median(in_run_share):.2f} % of wall time, "
                f"write after it {statistics.median(write_s) * 1e3:.0f} ms = "
                f"{100 * statistics.median(write_share):.1f} % of wall time; "
                f"median wall {on_s:.2f} s with, {off_s:.2f} s without ({100 * (on_s / off_s - 1):+.1f} %)"
            )
        svc.recordings.enabled = True


if __name__ == "__main__":
    main()
