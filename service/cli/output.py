"""Every line the commands print, in one place: results and tables on stdout (or JSON with --json),
progress and refusals on stderr (stdout stays clean for the token's last line, --json and exports)."""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path
from typing import Any


def error(message: str) -> None:
    """A refusal or failure: one line on stderr."""
    print(f"ripplecal: {message}", file=sys.stderr)


def note(message: str) -> None:
    """A line on stderr without the program's name (e.g. a missing row named with its database)."""
    print(message, file=sys.stderr)


def line(text: str = "") -> None:
    print(text)


def as_json(value: Any) -> None:
    print(json.dumps(value, indent=1))


# --- start ---------------------------------------------------------------------------------------------
def database_opened(path: Path | str) -> None:
    print(f"ripplecal: database {path}", file=sys.stderr, flush=True)


def starting_bench(bench_file: str | None) -> None:
    print(f"starting the {'bench ' + bench_file if bench_file else 'emulated bench'} ...", file=sys.stderr, flush=True)


def serving(version: str, host: str, port: int, scheme: str = "http") -> None:
    print(f"ripplecal {version}: dashboard at {scheme}://{host}:{port}/", flush=True)


# --- progress (stderr) ---------------------------------------------------------------------------------
class JobProgress:
    """A job's state changes and its accepted windows (plant time, residual), as the engine publishes
    them; a window line at most every 0.5 s (grid: 360 windows)."""

    def __init__(self, out=None):
        self.out = out
        self._last_line = -math.inf
        self._last_state: str | None = None  # a state is printed once, however often it is published

    def queued(self, job_id: int) -> int:
        print(f"job {job_id}: queued", file=self._file, flush=True)
        self._last_state = "queued"
        return job_id

    @property
    def _file(self):
        return self.out if self.out is not None else sys.stderr

    def event(self, job_id: int, kind: str, event: dict[str, Any]) -> bool:
        """One published event; True if it is this job's (its state is then read again)."""
        if event.get("job_id") != job_id:
            return False
        if kind == "job.state" and event["state"] != self._last_state:
            self._last_state = event["state"]
            print(
                f"job {job_id}: {event['state']}" + (f" ({event['error']})" if event.get("error") else ""),
                file=self._file,
                flush=True,
            )
        elif kind == "job.progress" and (time.monotonic() - self._last_line >= 0.5):
            self._last_line = time.monotonic()
            residual = event["residual_fs"]
            dbfs = 20 * math.log10(residual) if residual > 0 else -math.inf
            print(
                f"  plant time {event['plant_time_s']:8.3f} s   residual {residual:.3e} FS ({dbfs:6.1f} dBFS)",
                file=self._file,
                flush=True,
            )
        return True


class SweepProgress:
    """A sweep's progress line, each time its count of points done or its state changes."""

    def __init__(self):
        self._last: tuple | None = None

    def show(self, sweep_id: int, s: dict[str, Any]) -> None:
        if (s["done_points"], s["state"]) != self._last:
            self._last = (s["done_points"], s["state"])
            print(
                f"sweep {sweep_id}: {s['done_points']}/{s['total_points']} points, {s['state']}",
                file=sys.stderr,
                flush=True,
            )


# --- identify, sweep -------------------------------------------------------------------------------------
def identification(
    op, job_id: int, job: dict[str, Any], result: dict[str, Any] | None, db_path: str, as_json_: bool
) -> None:
    if as_json_:
        as_json({"job_id": job_id, "state": job["state"], "error": job["error"], "result": result})
    elif result is None or job["state"] != "done":
        print(f"identification {job['state']}: {job['error']}", file=sys.stderr)
    else:
        print(f"operating point   {op.label()}")
        print(f"method            {result['method']} ({result['status']}: {result['message']})")
        print(f"gamma             {result['gamma_deg']:.3f} deg")
        print(f"delta             {result['delta_deg']:.2f} deg")
        print(f"theta             cos {result['theta_cos']:.6f} rad, sin {result['theta_sin']:.6f} rad")
        print(f"suppression       {result['suppression_db']:.1f} dB (h = {result['harmonic_order']})")
        print(f"plant time        {result['plant_time_s']:.3f} s")
        print(f"result id         {result['id']} (job {job_id}) in {db_path}")


def sweep_outcome(sweep_id: int, sweep: dict[str, Any], wall_s: float, as_json_: bool) -> None:
    if as_json_:
        as_json(
            {
                "sweep_id": sweep_id,
                "state": sweep["state"],
                "map_id": sweep["map_id"],
                "done_points": sweep["done_points"],
                "failed_points": sweep["failed_points"],
                "total_points": sweep["total_points"],
            }
        )
    else:
        print(
            f"sweep {sweep_id} {sweep['state']} in {wall_s:.1f} s wall; "
            f"{sweep['failed_points']} failed point(s); map {sweep['map_id']}"
        )


# --- tokens, schedules -----------------------------------------------------------------------------------
def token_created(token_id: int, role: str, token: str) -> None:
    print(f"token id {token_id}, role {role} (shown once; stored hashed)")
    print(token)


def tokens(rows: list[dict[str, Any]]) -> None:
    for t in rows:
        print(
            f"{t['id']:>4}  {t['role']:<8}  {t['label']:<20}  created {t['created_at']}"
            + (f"  revoked {t['revoked_at']}" if t["revoked_at"] else "")
        )


def schedule_added(s, db_path: str) -> None:
    print(f"schedule {s.id} '{s.name}': {s.cron} ({s.timezone}), next {', '.join(s.next_runs[:3]) or '(disabled)'}")
    print(f"stored in {db_path}; a running service on this database fires it")


def schedules(rows: list, db_path: str) -> None:
    """One line per schedule (its next firing and last run); `rows` are ScheduleOut with one of each."""
    if not rows:
        print(f"no schedules in {db_path}")
    for s in rows:
        last = s.runs[0] if s.runs else None
        print(
            f"{s.id:>4}  {s.name:<24}  {s.cron:<16} {s.timezone:<16} {'on ' if s.enabled else 'off'}  "
            f"next {s.next_runs[0] if s.next_runs else '-':<25}  "
            + (
                f"last {last.due_at} {last.outcome}" + (f" sweep {last.sweep_id}" if last.sweep_id else "")
                if last
                else "never fired"
            )
        )


# --- maps, sweeps --------------------------------------------------------------------------------------
def maps(rows: list) -> None:
    if not rows:
        print("no maps yet: a sweep builds one when it ends")
        return
    print(f"{'id':>5}  {'sweep':>5}  {'method':<8}  {'h':>2}  {'ok/cells':>8}  {'created':<25}  bench")
    for m in rows:
        print(
            f"{m.id:>5}  {m.sweep_id if m.sweep_id is not None else '-':>5}  {m.method:<8}  {m.harmonic_order:>2}  "
            f"{m.status_counts.get('ok', 0):>3}/{len(m.cells):<4}  {m.created_at:<25}  {m.bench_identity}"
        )


def lut_downloaded(receipt, lut, identity: str, throwaway: bool = False) -> None:
    filled = f", {lut.filled_cells} filled" if lut.fill else ", fill left out"
    if lut.injection_off_cells:
        filled += f", {lut.injection_off_cells} injection off"
    where = (
        "in the drive of an emulated bench of this command's own (gone now: give --bench FILE to load a bench's "
        "drive; a running `ripplecal serve` downloads with POST /api/v1/maps/{id}/download)"
        if throwaway
        else f"in the drive of {identity}"
    )
    print(
        f"map {receipt.map_id}: {receipt.bytes} bytes ({receipt.valid_cells} of {receipt.cells} cells ok{filled}, "
        f"{lut.interpolation} interpolation, h = {receipt.harmonic_order}{', forced' if receipt.forced else ''}) "
        f"{where}; CRC-32 read back {receipt.crc32}"
    )


def sweep_details(sw) -> None:
    p = sw.progress
    title = f"refinement {sw.id} of map {sw.source_map_id}" if sw.kind == "refinement" else f"sweep {sw.id}"
    print(f"{title}: {sw.state}, {sw.method}, h = {sw.harmonic_order}, bench {sw.bench_identity}")
    print(f"grid      torque {sw.grid['torque_nm']} Nm, speed {sw.grid['speed_rpm']} rpm, udc {sw.grid['udc_v']} V")
    print(
        f"progress  {p['done']}/{p['total']} {'cells' if sw.refinement else 'points'}: {p['ok']} ok, "
        f"{p['below_target']} below target, {p['no_authority']} no authority, {p['failed']} failed; plant time "
        f"{sw.plant_time_s:.1f} s"
    )
    if (ref := sw.refinement) is not None:
        print(
            f"refining  {len(ref.rounds)} round(s) validated, {ref.phase}; {ref.cells_added} of max {ref.max_cells} cells "
            "identified (new and re-measured)" + (f"; stopped: {ref.stopped}" if ref.stopped else "")
        )
    print(f"map       {sw.map_id if sw.map_id is not None else '-'}")
    if sw.pause_reason:
        print(f"paused    {sw.pause_reason}")
    if sw.error:
        print(f"error     {sw.error}")
    for pt in sw.points or []:
        r, op = pt.result, pt.operating_point
        numbers = (
            f"gamma {r.gamma_deg:6.3f} deg  delta {r.delta_deg:7.2f} deg  {r.suppression_db:5.1f} dB"
            if r.gamma_deg is not None and r.suppression_db is not None
            else ""
        )
        print(
            f"  {op.label():<28} {pt.state:<13} {numbers}"
            + (f"  {r.message}" if pt.state != "ok" and r.message else "")
        )


def sweeps(rows: list) -> None:
    if not rows:
        print("no sweeps yet")
        return
    print(f"{'id':>5}  {'kind':<20}  {'state':<11}  {'method':<8}  {'cells':>9}  {'failed':>6}  {'map':>5}  created")
    for sw in rows:
        print(
            f"{sw.id:>5}  {sweep_kind(sw):<20}  {sw.state:<11}  {sw.method:<8}  "
            f"{sw.progress['done']:>4}/{sw.progress['total']:<4}  {sw.progress['failed']:>6}  "
            f"{sw.map_id if sw.map_id is not None else '-':>5}  {sw.created_at}"
        )


def sweep_kind(sw) -> str:
    """ "sweep", or "refinement of map 4": what the run is, as the user started it."""
    return f"refinement of map {sw.source_map_id}" if sw.kind == "refinement" else "sweep"


# --- paper -------------------------------------------------------------------------------------------------
def paper_started(out_dir: str) -> None:
    print(f"ripplecal paper: measuring Fig. 8-12 on the emulated bench into {out_dir} ...", file=sys.stderr, flush=True)


def paper(results: dict[str, Any], out_dir: str) -> None:
    f8, f9, f11, f12 = (results[k] for k in ("fig8", "fig9", "fig11", "fig12"))
    print(
        f"fig8  grid minimum {f8['grid_min']['gamma_deg']:g} deg / {f8['grid_min']['delta_deg']:g} deg, "
        f"fit {f8['fit']['gamma_deg']:.2f} deg / {f8['fit']['delta_deg']:.1f} deg (paper 3 / 280)"
    )
    print(f"fig9  adaptive {f9['gamma_deg']:.2f} deg / {f9['delta_deg']:.2f} deg (paper 2.84 / 279.17)")
    print(
        f"fig10 suppression {results['fig10']['suppression_db']:.1f} dB, peak |u*| "
        f"{results['fig10']['u_max_increase_pct']:+.3f} %"
    )
    print(
        f"fig11 time to 40 dB coupled {f11['coupled']['time_to_40db_s']} s, decoupled {f11['decoupled']['time_to_40db_s']} s"
    )
    print(
        f"fig12 coupled {f12['coupled']['suppression_db']} dB (gamma limited: {f12['coupled']['gamma_limited']}), "
        f"decoupled {f12['decoupled']['suppression_db']} dB, i_d harmonic {f12['decoupled']['i_d_harmonic_a']} A"
    )
    print(f"wrote {Path(out_dir) / 'report.html'} and results.json in {results['meta']['wall_time_s']:.1f} s wall")
