"""`ripplecal` command line: serve, identify, sweep, export, token, schedule, maps, sweeps, paper.

identify, sweep and `maps download` run in this process against the bench (emulated unless --bench
names a bench settings file), through the same engine the REST API uses, and store into the database.
The database is resolved once, made absolute and printed (stderr) at start: --db, else
RIPPLECAL_SERVER__DB_PATH, else the per-user default ($XDG_DATA_HOME or ~/.local/share)/ripplecal/ripplecal.db,
the same for every command whatever the working directory.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import math
import logging
import os
import sqlite3
import sys
import time
from datetime import datetime
from pathlib import Path

from drivers.lut_image import DEFAULT_INTERPOLATION, INTERPOLATIONS
from service import __version__
from service.identification.registry import METHODS
from service.maps.lut_export import EXPORT_FORMATS
from service.settings import Settings, SettingsError, load_settings
from service.store.storage import Storage, StorageError


class StartError(Exception):
    """An operator error at start (a database or bench file that cannot be used): one line naming the
    file and what is wrong, exit code 2."""


def _floats(text: str) -> list[float]:
    try:
        return [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def _add_bench_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--emulate", action="store_true", help="run against plant_emulator (default without --bench)")
    p.add_argument("--scenario", help="emulator scenario name or TOML file (default paper-bench)")
    p.add_argument("--seed", type=int, help="emulator seed: draws the truth within the scenario's ranges")
    p.add_argument("--speedup", type=float, help="emulator speed: 0 = as fast as the DAQ is read, 1 = real time")
    p.add_argument("--bench", metavar="FILE", help="settings file naming a real bench's endpoints")
    p.add_argument("--settings", metavar="FILE", help="settings TOML (defaults + RIPPLECAL_* environment otherwise)")
    p.add_argument("--db", metavar="PATH", help="SQLite database file")


def _settings(args) -> Settings:
    path = args.bench or getattr(args, "settings", None)
    overrides = {"server.db_path": getattr(args, "db", None)}
    if getattr(args, "bench", None):
        overrides["bench_mode"] = "bench"
    elif getattr(args, "emulate", False) or hasattr(args, "scenario"):
        if getattr(args, "emulate", False):
            overrides["bench_mode"] = "emulate"
        overrides.update({"emulator.scenario": getattr(args, "scenario", None), "emulator.seed": getattr(args, "seed", None),
                          "emulator.speedup": getattr(args, "speedup", None)})
    for key in ("host", "port"):
        if getattr(args, key, None) is not None:
            overrides[f"server.{key}"] = getattr(args, key)
    settings = load_settings(path, overrides=overrides)
    if getattr(args, "bench", None):
        _check_bench_file(args.bench, settings)
        if "bench_name" not in settings.model_fields_set:
            # a bench file without bench_name: the bench is called after its file
            settings = settings.model_copy(update={"bench_name": Path(args.bench).stem})
    settings.server.db_path = resolve_db_path(settings.server.db_path)
    return settings


def _check_bench_file(path: str, settings: Settings) -> None:
    """A real bench needs its DAQ and supply ports: said at start, naming the file, not when the bench connects."""
    missing = [what for what, url in (("DAQ port ([daq] url)", settings.daq.url),
                                      ("DC supply port ([supply] url)", settings.supply.url)) if not url]
    if missing:
        raise SettingsError(f"bench file {Path(path).absolute()} names no {' and no '.join(missing)}: a real bench "
                            'needs both, e.g. [daq] url = "/dev/ttyUSB0" and [supply] url = "socket://192.168.0.20:5025"')


def _open_database(settings: Settings) -> Storage:
    """The command's database, opened and migrated at start, then printed (stderr: stdout stays clean for
    the token's last line, --json and exports). What makes it unusable is a StartError naming the file."""
    path = Path(settings.server.db_path)
    if path.is_dir():
        raise StartError(f"database {path} is a directory: --db must name a database file, e.g. {path / 'ripplecal.db'}")
    if path.exists() and not os.access(path, os.R_OK | os.W_OK):
        raise StartError(f"database {path} cannot be read and written by this user: check its permissions")
    try:
        storage = Storage(path, busy_timeout_s=settings.server.db_busy_timeout_s)
    except StorageError as exc:                 # a newer schema, a failed migration; locked, read-only, full
        raise StartError(str(exc)) from None
    except sqlite3.DatabaseError as exc:        # e.g. "file is not a database": a text file, another format
        raise StartError(f"database {path} is not a database SQLite can use ({exc}): --db must name a ripplecal "
                         "database or a new file") from None
    except (FileExistsError, NotADirectoryError) as exc:
        raise StartError(f"database {path} cannot be created: {exc.filename} is a file, not a directory") from None
    except OSError as exc:
        raise StartError(f"database {path} cannot be created: {exc.strerror or type(exc).__name__}"
                         + (f" ({exc.filename})" if exc.filename else "")) from None
    print(f"ripplecal: database {path}", file=sys.stderr, flush=True)
    return storage


def resolve_db_path(path: str) -> str:
    """Absolute once, at start: a relative --db or RIPPLECAL_SERVER__DB_PATH is taken against this working directory."""
    return str(Path(path).expanduser().absolute())


def cmd_serve(args) -> int:
    import signal

    import uvicorn

    from service.api.app import create_app
    from service.calibration_service import CalibrationService
    from service.store.db_claim import DatabaseClaim
    settings = _settings(args)
    # before the database is migrated or recovered: a second serve on this database ends here, in one line
    claim: DatabaseClaim | None = DatabaseClaim(settings.server.db_path, settings.server.port)
    try:
        claim.acquire()                     # DatabaseInUse (a StorageError) names the holder: one line, exit 2
    except OSError:
        claim = None                        # no file can be made there: opening the database names why
    try:
        service = CalibrationService(settings, storage=_open_database(settings), claim=claim)
    except BaseException:
        if claim is not None:
            claim.release()
        raise
    app = create_app(service)

    class Server(uvicorn.Server):
        """uvicorn's own signal handling, plus the signal's name for the sweeps it interrupts."""

        def handle_exit(self, sig: int, frame) -> None:
            service.shutdown_reason = f"service shut down ({signal.Signals(sig).name})"
            service.broker.close()      # open SSE streams end now: uvicorn waits for them before shutting down
            super().handle_exit(sig, frame)

    print(f"ripplecal {__version__}: dashboard at http://{settings.server.host}:{settings.server.port}/", flush=True)
    # timeout_graceful_shutdown: a backstop for a connection that does not end by itself
    server = Server(uvicorn.Config(app, host=settings.server.host, port=settings.server.port, log_level="info",
                                   timeout_graceful_shutdown=10))
    logging.getLogger("uvicorn.access").addFilter(_path_without_query)      # after uvicorn's logging config
    try:
        server.run()
    except KeyboardInterrupt:
        # uvicorn re-raises the Ctrl+C it handled once the shutdown is done: exit as interrupted, quietly
        return 130
    return 0


def _path_without_query(record: logging.LogRecord) -> bool:
    """uvicorn's access log line without the query string: a token a client puts in a query is not logged.
    Its args are (client, method, path with query, HTTP version, status)."""
    if isinstance(record.args, tuple) and len(record.args) == 5 and isinstance(record.args[2], str):
        client, method, path, version, status = record.args
        record.args = (client, method, path.split("?", 1)[0], version, status)
    return True


def _wait(predicate, deadline: float, what: str):
    while time.monotonic() < deadline:
        value = predicate()
        if value is not None:
            return value
        time.sleep(0.05)
    raise TimeoutError(f"{what} did not finish before the timeout")


JOB_FINAL = ("done", "failed", "cancelled")


def _follow_job(service, submit, timeout_s: float, out=sys.stderr) -> dict:
    """Submit a job and print its state changes and each accepted window (plant time, residual) as the
    engine publishes them (the service's EventBroker, in this process) until it ends. The job row is
    read after every event and at least once a second, so a lost event never hangs the wait."""
    async def follow() -> dict:
        token = service.broker.subscribe()       # before submitting: no early event is missed
        queue = token[1]
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        last_line = -math.inf
        try:
            job_id = submit()
            print(f"job {job_id}: queued", file=out, flush=True)
            while True:
                job = service.storage.get_job(job_id)
                if job["state"] in JOB_FINAL:
                    return job
                remaining = deadline - loop.time()
                if remaining <= 0:
                    raise TimeoutError(f"identification job {job_id} did not finish within {timeout_s:g} s "
                                       "(--timeout); it was cancelled")
                try:
                    kind, data = await asyncio.wait_for(queue.get(), timeout=min(1.0, remaining))
                except asyncio.TimeoutError:
                    continue
                event = json.loads(data)
                if event.get("job_id") != job_id:
                    continue
                if kind == "job.state" and event["state"] != "queued":
                    print(f"job {job_id}: {event['state']}" + (f" ({event['error']})" if event.get("error") else ""),
                          file=out, flush=True)
                elif kind == "job.progress" and (loop.time() - last_line >= 0.5):   # grid: 360 windows; a line per 0.5 s
                    last_line = loop.time()
                    residual = event["residual_fs"]
                    dbfs = 20 * math.log10(residual) if residual > 0 else -math.inf
                    print(f"  plant time {event['plant_time_s']:8.3f} s   residual {residual:.3e} FS ({dbfs:6.1f} dBFS)",
                          file=out, flush=True)
        finally:
            service.broker.unsubscribe(token)
    return asyncio.run(follow())


def cmd_identify(args) -> int:
    from service.calibration_service import CalibrationService
    from service.runs.identify import parse_options
    from service.api.public import result_public
    from service.model.operating_point import OperatingPoint
    settings = _settings(args)
    op = OperatingPoint(torque_nm=args.torque, speed_rpm=args.speed, udc_v=args.udc)
    options = parse_options(args.method, _json_option(args.options))
    storage = _open_database(settings)
    print(f"starting the {'bench ' + args.bench if args.bench else 'emulated bench'} ...", file=sys.stderr, flush=True)
    with CalibrationService(settings, storage=storage) as service:
        job = _follow_job(service, lambda: service.engine.submit_identification(op, args.method, options), args.timeout)
        job_id = job["id"]
        result = result_public(service.storage.get_result(job["result_id"])).model_dump() if job["result_id"] else None
    if args.json:
        print(json.dumps({"job_id": job_id, "state": job["state"], "error": job["error"], "result": result}, indent=1))
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
        print(f"result id         {result['id']} (job {job_id}) in {settings.server.db_path}")
    return 0 if job["state"] == "done" else 1


def _json_option(text: str | None) -> dict:
    if not text:
        return {}
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"--options is not valid JSON ({exc.msg} at character {exc.pos}): {text!r}") from None
    if not isinstance(value, dict):
        raise ValueError(f"--options must be a JSON object, e.g. '{{\"mu_per_s\": 10}}', got {text!r}")
    return value


def cmd_sweep(args) -> int:
    from service.calibration_service import CalibrationService
    from service.runs.identify import parse_options
    from service.runs.plans import Grid
    settings = _settings(args)
    grid = Grid(torque_nm=args.torque, speed_rpm=args.speed, udc_v=args.udc)
    options = parse_options(args.method, _json_option(args.options))
    storage = _open_database(settings)
    started = time.monotonic()
    with CalibrationService(settings, storage=storage) as service:
        sweep_id = service.engine.submit_sweep(grid, args.method, options)
        last = None

        def finished():
            nonlocal last
            s = service.storage.get_sweep(sweep_id)
            if (s["done_points"], s["state"]) != last:
                last = (s["done_points"], s["state"])
                print(f"sweep {sweep_id}: {s['done_points']}/{s['total_points']} points, {s['state']}", file=sys.stderr,
                      flush=True)
            return s if s["state"] in ("done", "failed", "cancelled") else None
        sweep = _wait(finished, time.monotonic() + args.timeout, f"sweep {sweep_id}")
    if args.json:
        print(json.dumps({"sweep_id": sweep_id, "state": sweep["state"], "map_id": sweep["map_id"],
                          "done_points": sweep["done_points"], "failed_points": sweep["failed_points"],
                          "total_points": sweep["total_points"]}, indent=1))
    else:
        print(f"sweep {sweep_id} {sweep['state']} in {time.monotonic() - started:.1f} s wall; "
              f"{sweep['failed_points']} failed point(s); map {sweep['map_id']}")
    return 0 if sweep["state"] == "done" and sweep["failed_points"] == 0 else 1


def cmd_export(args) -> int:
    from service.maps.lut_export import export_map
    from service.api.public import map_public
    settings = _settings(args)
    m = map_public(_open_database(settings), args.map_id)
    if m is None:
        print(f"map {args.map_id} does not exist in {settings.server.db_path}", file=sys.stderr)
        return 2
    text = export_map(m.model_dump(), args.format)
    if args.out:
        Path(args.out).write_text(text)
        print(f"wrote {args.out}")
    else:
        sys.stdout.write(text)
    return 0


def cmd_token(args) -> int:
    storage = _open_database(_settings(args))
    if args.token_cmd == "create":
        token_id, token = storage.create_token(args.role, args.label or "")
        print(f"token id {token_id}, role {args.role} (shown once; stored hashed)")
        print(token)
    elif args.token_cmd == "revoke":
        if not storage.revoke_token(args.token_id):
            print(f"token {args.token_id} does not exist or is already revoked", file=sys.stderr)
            return 1
        print(f"token {args.token_id} revoked")
    else:
        for t in storage.list_tokens():
            print(f"{t['id']:>4}  {t['role']:<8}  {t['label']:<20}  created {t['created_at']}"
                  + (f"  revoked {t['revoked_at']}" if t["revoked_at"] else ""))
    return 0


def cmd_schedule(args) -> int:
    """Schedules live in the database: a running `serve` on the same --db picks up a new one on its
    next pass (schedules.tick_s), as it reads tokens made by `token create`."""
    from pydantic import TypeAdapter, ValidationError

    from service.api.schemas import SweepCreate
    from service.api.public import schedule_public
    from service.runs.schedules import (check_cron, check_timezone, create_schedule, delete_schedule, next_runs,
                                   iso, utc_now)
    settings = _settings(args)
    if args.schedule_cmd == "preview":
        cron, zone = check_cron(args.cron), check_timezone(args.timezone)
        start = datetime.fromisoformat(args.start) if args.start else utc_now()
        for t in next_runs(cron, zone, start, args.count):
            print(iso(t))
        return 0
    storage = _open_database(settings)
    now = utc_now()
    if args.schedule_cmd == "add":
        try:
            sweep = TypeAdapter(SweepCreate).validate_python({
                "grid": {"torque_nm": args.torque, "speed_rpm": args.speed, "udc_v": args.udc}, "method": args.method,
                "options": json.loads(args.options) if args.options else {}, "confirm_large": args.confirm_large})
        except ValidationError as exc:
            raise ValueError("; ".join(f"{'.'.join(str(x) for x in e['loc'])}: {e['msg']}" for e in exc.errors())) from None
        schedule_id = create_schedule(storage, settings, now, args.name, args.cron, args.timezone, sweep,
                                      enabled=not args.disabled)
        s = schedule_public(storage, storage.get_schedule(schedule_id), now)
        print(f"schedule {s.id} '{s.name}': {s.cron} ({s.timezone}), next {', '.join(s.next_runs[:3]) or '(disabled)'}")
        print(f"stored in {settings.server.db_path}; a running service on this database fires it")
    elif args.schedule_cmd == "rm":
        try:
            delete_schedule(storage, now, args.schedule_id)
        except KeyError:
            print(f"schedule {args.schedule_id} does not exist in {settings.server.db_path}", file=sys.stderr)
            return 1
        print(f"schedule {args.schedule_id} deleted")
    else:
        rows = storage.list_schedules()
        if args.json:
            print(json.dumps([schedule_public(storage, r, now).model_dump() for r in rows], indent=1))
            return 0
        if not rows:
            print(f"no schedules in {settings.server.db_path}")
        for r in rows:
            s = schedule_public(storage, r, now, next_count=1, run_count=1)
            last = s.runs[0] if s.runs else None
            print(f"{s.id:>4}  {s.name:<24}  {s.cron:<16} {s.timezone:<16} {'on ' if s.enabled else 'off'}  "
                  f"next {s.next_runs[0] if s.next_runs else '-':<25}  "
                  + (f"last {last.due_at} {last.outcome}" + (f" sweep {last.sweep_id}" if last.sweep_id else "")
                     if last else "never fired"))
    return 0


def _storage(args) -> Storage:
    return _open_database(_settings(args))


def cmd_maps(args) -> int:
    if args.maps_cmd == "download":
        return _download_map(args)
    from service.api.public import map_public
    storage = _storage(args)
    maps = [map_public(storage, row["id"]) for row in storage.list_maps(args.limit)]
    if args.json:
        print(json.dumps([m.model_dump(exclude={"cells"}) for m in maps], indent=1))
        return 0
    if not maps:
        print("no maps yet: a sweep builds one when it ends")
        return 0
    print(f"{'id':>5}  {'sweep':>5}  {'method':<8}  {'h':>2}  {'ok/cells':>8}  {'created':<25}  bench")
    for m in maps:
        print(f"{m.id:>5}  {m.sweep_id if m.sweep_id is not None else '-':>5}  {m.method:<8}  {m.harmonic_order:>2}  "
              f"{m.status_counts.get('ok', 0):>3}/{len(m.cells):<4}  {m.created_at:<25}  {m.bench_identity}")
    return 0


def _download_map(args) -> int:
    """The map's LUT into the drive over the bench, as POST /maps/{id}/download does (same rules: no ok
    cell is refused, a map with cells that would inject nothing under the chosen fill needs --force;
    --no-fill leaves the filled cells out, --interpolation names the drive's mode). It opens the bench itself: run it with no
    `ripplecal serve` using the same bench (two masters on one bus and one DAQ port would fight over
    it); without --bench it downloads into an emulator of its own."""
    from service.runs import lut_download
    from service.bench.bench import BenchError
    from service.calibration_service import CalibrationService
    settings = _settings(args)
    storage = _open_database(settings)
    try:                                       # refused before the bench is started
        lut = lut_download.prepare(storage, args.map_id, args.force, fill=args.fill,
                                   interpolation=args.interpolation)
    except lut_download.MapNotFound as exc:
        print(f"ripplecal: {exc} in {settings.server.db_path}", file=sys.stderr)
        return 2
    except (lut_download.LutRefused, lut_download.PartialMap) as exc:
        print(f"ripplecal: {exc}", file=sys.stderr)
        return 2
    print(f"starting the {'bench ' + args.bench if args.bench else 'emulated bench'} ...", file=sys.stderr, flush=True)
    with CalibrationService(settings, storage=storage) as service:
        try:
            receipt = lut_download.send(service.bench, lut)
        except BenchError as exc:
            print(f"ripplecal: {exc}", file=sys.stderr)
            return 1
        except Exception as exc:   # SDO abort / timeout: the drive refused or did not answer
            print(f"ripplecal: drive refused the LUT: {exc}", file=sys.stderr)
            return 1
        identity = service.bench.identity
    if args.json:
        print(json.dumps({**receipt.model_dump(), **lut.receipt_fields(), "bench": identity}, indent=1))
    else:
        filled = f", {lut.filled_cells} filled" if lut.fill else ", fill left out"
        print(f"map {receipt.map_id}: {receipt.bytes} bytes ({receipt.valid_cells} of {receipt.cells} cells ok{filled}, "
              f"{lut.interpolation} interpolation, h = {receipt.harmonic_order}{', forced' if receipt.forced else ''}) "
              f"in the drive of {identity}; CRC-32 read back {receipt.crc32}")
    return 0


def cmd_sweeps(args) -> int:
    from service.api.public import sweep_public
    storage = _storage(args)
    if args.sweeps_cmd == "show":
        row = storage.get_sweep(args.sweep_id)
        if row is None:
            print(f"ripplecal: sweep {args.sweep_id} does not exist in {storage.path}", file=sys.stderr)
            return 2
        sw = sweep_public(storage, row, with_points=True)
        if args.json:
            print(json.dumps(sw.model_dump(), indent=1))
            return 0
        p = sw.progress
        print(f"sweep {sw.id}: {sw.state}, {sw.method}, h = {sw.harmonic_order}, bench {sw.bench_identity}")
        print(f"grid      torque {sw.grid['torque_nm']} Nm, speed {sw.grid['speed_rpm']} rpm, udc {sw.grid['udc_v']} V")
        print(f"progress  {p['done']}/{p['total']} points: {p['ok']} ok, {p['below_target']} below target, "
              f"{p['no_authority']} no authority, {p['failed']} failed; plant time {sw.plant_time_s:.1f} s")
        print(f"map       {sw.map_id if sw.map_id is not None else '-'}")
        if sw.pause_reason:
            print(f"paused    {sw.pause_reason}")
        if sw.error:
            print(f"error     {sw.error}")
        for pt in sw.points or []:
            r, op = pt.result, pt.operating_point
            numbers = (f"gamma {r.gamma_deg:6.3f} deg  delta {r.delta_deg:7.2f} deg  {r.suppression_db:5.1f} dB"
                       if r.gamma_deg is not None and r.suppression_db is not None else "")
            print(f"  {op.label():<28} {pt.state:<13} {numbers}" + (f"  {r.message}" if pt.state != "ok" and r.message else ""))
        return 0
    sweeps = [sweep_public(storage, row) for row in storage.list_sweeps(args.limit)]
    if args.json:
        print(json.dumps([sw.model_dump() for sw in sweeps], indent=1))
        return 0
    if not sweeps:
        print("no sweeps yet")
        return 0
    print(f"{'id':>5}  {'state':<11}  {'method':<8}  {'points':>9}  {'failed':>6}  {'map':>5}  created")
    for sw in sweeps:
        print(f"{sw.id:>5}  {sw.state:<11}  {sw.method:<8}  {sw.progress['done']:>4}/{sw.progress['total']:<4}  "
              f"{sw.progress['failed']:>6}  {sw.map_id if sw.map_id is not None else '-':>5}  {sw.created_at}")
    return 0


def cmd_paper(args) -> int:
    """The paper's Fig. 8-12 on emulated benches of its own (service/paper); never a real bench."""
    from service.paper.report import run
    command = "ripplecal paper --out " + args.out + (" --quick" if args.quick else "")
    print(f"ripplecal paper: measuring Fig. 8-12 on the emulated bench into {args.out} ...", file=sys.stderr, flush=True)
    results = run(args.out, quick=args.quick, command=command)
    f8, f9, f11, f12 = (results[k] for k in ("fig8", "fig9", "fig11", "fig12"))
    print(f"fig8  grid minimum {f8['grid_min']['gamma_deg']:g} deg / {f8['grid_min']['delta_deg']:g} deg, "
          f"fit {f8['fit']['gamma_deg']:.2f} deg / {f8['fit']['delta_deg']:.1f} deg (paper 3 / 280)")
    print(f"fig9  adaptive {f9['gamma_deg']:.2f} deg / {f9['delta_deg']:.2f} deg (paper 2.84 / 279.17)")
    print(f"fig10 suppression {results['fig10']['suppression_db']:.1f} dB, peak |u*| "
          f"{results['fig10']['u_max_increase_pct']:+.3f} %")
    print(f"fig11 time to 40 dB coupled {f11['coupled']['time_to_40db_s']} s, decoupled {f11['decoupled']['time_to_40db_s']} s")
    print(f"fig12 coupled {f12['coupled']['suppression_db']} dB (gamma limited: {f12['coupled']['gamma_limited']}), "
          f"decoupled {f12['decoupled']['suppression_db']} dB, i_d harmonic {f12['decoupled']['i_d_harmonic_a']} A")
    print(f"wrote {Path(args.out) / 'report.html'} and results.json in {results['meta']['wall_time_s']:.1f} s wall")
    return 0


# --- the parser: one small function per command (each keeps its options to itself) --------------------
def _db_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--db", metavar="PATH", help="SQLite database file (default: RIPPLECAL_SERVER__DB_PATH, "
                                                  "else ~/.local/share/ripplecal/ripplecal.db)")
    p.add_argument("--settings", metavar="FILE", help="settings TOML")


def _parser_serve(sub) -> None:
    p = sub.add_parser("serve", help="run the REST API and dashboard")
    _add_bench_args(p)
    p.add_argument("--host", help="bind address (default 127.0.0.1)")
    p.add_argument("--port", type=int, help="port (default 8000)")
    p.set_defaults(func=cmd_serve)


def _run_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--method", choices=list(METHODS), default="adaptive")
    p.add_argument("--options", help="method options as JSON, e.g. '{\"mu_per_s\": 10}'")
    p.add_argument("--timeout", type=float, default=3600.0, help="give up after this many seconds")
    p.add_argument("--json", action="store_true", help="print the outcome as JSON (progress stays on stderr)")


def _parser_identify(sub) -> None:
    p = sub.add_parser("identify", help="identify theta* at one operating point (prints its progress on stderr)")
    _add_bench_args(p)
    p.add_argument("--torque", type=float, required=True, help="torque command, Nm")
    p.add_argument("--speed", type=float, required=True, help="speed, rpm")
    p.add_argument("--udc", type=float, default=12.0, help="DC-link voltage, V (default 12)")
    _run_args(p)
    p.set_defaults(func=cmd_identify)


def _parser_sweep(sub) -> None:
    p = sub.add_parser("sweep", help="identify over a grid and build a map")
    _add_bench_args(p)
    p.add_argument("--torque", type=_floats, required=True, help="torques, Nm, comma-separated")
    p.add_argument("--speed", type=_floats, required=True, help="speeds, rpm, comma-separated")
    p.add_argument("--udc", type=_floats, default=[12.0], help="DC-link voltages, V, comma-separated")
    _run_args(p)
    p.set_defaults(func=cmd_sweep)


def _parser_export(sub) -> None:
    p = sub.add_parser("export", help="export a map as a LUT")
    p.add_argument("map_id", type=int)
    p.add_argument("--format", choices=list(EXPORT_FORMATS), default="csv")
    p.add_argument("--out", help="file to write (stdout otherwise)")
    _db_args(p)
    p.set_defaults(func=cmd_export, bench=None)


def _parser_token(sub) -> None:
    p = sub.add_parser("token", help="create, revoke or list API tokens")
    tsub = p.add_subparsers(dest="token_cmd", required=True)
    t = tsub.add_parser("create")
    t.add_argument("--role", choices=["viewer", "operator", "admin"], required=True)
    t.add_argument("--label")
    _db_args(t)
    t = tsub.add_parser("revoke")
    t.add_argument("token_id", type=int)
    _db_args(t)
    t = tsub.add_parser("list")
    _db_args(t)
    p.set_defaults(func=cmd_token, bench=None)

def _parser_schedule(sub) -> None:
    p = sub.add_parser("schedule", help="add, list, remove or preview scheduled sweeps")
    ssub = p.add_subparsers(dest="schedule_cmd", required=True)
    t = ssub.add_parser("add", help="a sweep at the times of a cron expression")
    t.add_argument("--name", required=True)
    t.add_argument("--cron", required=True, help="5 fields, e.g. '0 2 * * 1-5' (Debian cron semantics)")
    t.add_argument("--timezone", default="UTC", help="IANA time zone, e.g. Europe/Berlin (default UTC)")
    t.add_argument("--torque", type=_floats, required=True, help="torques, Nm, comma-separated")
    t.add_argument("--speed", type=_floats, required=True, help="speeds, rpm, comma-separated")
    t.add_argument("--udc", type=_floats, default=[12.0], help="DC-link voltages, V, comma-separated")
    t.add_argument("--method", choices=list(METHODS), default="adaptive")
    t.add_argument("--options", help="method options as JSON")
    t.add_argument("--confirm-large", action="store_true", help="allow a grid above safety.max_sweep_points_unconfirmed")
    t.add_argument("--disabled", action="store_true", help="store it disabled")
    t = ssub.add_parser("list", help="schedules with their next firing and last run")
    t.add_argument("--json", action="store_true")
    t = ssub.add_parser("rm", help="delete a schedule (its run history stays)")
    t.add_argument("schedule_id", type=int)
    t = ssub.add_parser("preview", help="the firings of a cron expression in a time zone")
    t.add_argument("cron")
    t.add_argument("--timezone", default="UTC")
    t.add_argument("--start", help="ISO 8601; without an offset: wall time in --timezone (default now)")
    t.add_argument("--count", type=int, default=10)
    for t in ssub.choices.values():
        _db_args(t)
    p.set_defaults(func=cmd_schedule, bench=None)


def _parser_maps(sub) -> None:
    p = sub.add_parser("maps", aliases=["map"], help="list maps; download one into the drive")
    msub = p.add_subparsers(dest="maps_cmd", required=True)
    t = msub.add_parser("list", help="the newest maps first")
    t.add_argument("--limit", type=int, default=50)
    t.add_argument("--json", action="store_true")
    _db_args(t)
    t.set_defaults(bench=None)
    t = msub.add_parser("download", help="the map's LUT into the drive (0x2001), CRC-32 read back; opens the bench "
                                         "itself: not while a `ripplecal serve` holds the same bench")
    t.add_argument("map_id", type=int)
    t.add_argument("--force", action="store_true", help="load a partial map (cells without an entry under the "
                                                             "chosen fill: no injection there)")
    t.add_argument("--no-fill", dest="fill", action="store_false",
                   help="leave the filled cells out (the drive then injects only at ok cells); default: with fill")
    t.add_argument("--interpolation", choices=list(INTERPOLATIONS), default=None,
                   help=f"what the drive interpolates between cells (default {DEFAULT_INTERPOLATION})")
    t.add_argument("--json", action="store_true")
    _add_bench_args(t)
    p.set_defaults(func=cmd_maps)


def _parser_sweeps(sub) -> None:
    p = sub.add_parser("sweeps", help="list sweeps; show one with its points")
    ssub = p.add_subparsers(dest="sweeps_cmd", required=True)
    t = ssub.add_parser("list", help="the newest sweeps first")
    t.add_argument("--limit", type=int, default=50)
    t.add_argument("--json", action="store_true")
    _db_args(t)
    t = ssub.add_parser("show", help="one sweep: progress, map, each point's result")
    t.add_argument("sweep_id", type=int)
    t.add_argument("--json", action="store_true")
    _db_args(t)
    p.set_defaults(func=cmd_sweeps, bench=None)


def _parser_paper(sub) -> None:
    p = sub.add_parser("paper", help="reproduce the paper's Fig. 8-12 on the emulated bench (report.html, results.json)")
    p.add_argument("--out", default="build/paper", help="output directory (default build/paper)")
    p.add_argument("--quick", action="store_true", help="coarser grid and shorter records (the test's run)")
    p.set_defaults(func=cmd_paper, bench=None)


COMMANDS = (_parser_serve, _parser_identify, _parser_sweep, _parser_export, _parser_token, _parser_schedule,
            _parser_maps, _parser_sweeps, _parser_paper)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ripplecal", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"ripplecal {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in COMMANDS:
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except (SettingsError, StartError, StorageError) as exc:   # StorageError: e.g. the database locked by another process
        print(f"ripplecal: {exc}", file=sys.stderr)
        return 2
    except (ValueError, TimeoutError) as exc:
        print(f"ripplecal: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:      # the service's context has already left the bench safe
        print("ripplecal: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        from service.bench.bench import BenchUnreachable      # here only: the bench's drivers take a while to import
        if isinstance(exc, BenchUnreachable):           # a real bench not reached: the run is refused at start
            print(f"ripplecal: {exc}", file=sys.stderr)
            return 2
        raise


if __name__ == "__main__":
    sys.exit(main())
