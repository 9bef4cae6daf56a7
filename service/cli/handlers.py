"""The commands: each resolves its settings and database (startup), calls the service layer and hands
what it got to `output`; the exit code is 0 done, 1 failed, 2 refused at start."""

from __future__ import annotations

import json
import logging
import signal
import sys
import time
from datetime import datetime
from pathlib import Path

from service import __version__
from service.cli import output
from service.cli.startup import StartError, json_option, open_database, settings_from, storage_from
from service.cli.waiting import follow
from service.store.engines import display_location

JOB_FINAL = ("done", "failed", "cancelled")


def cmd_serve(args) -> int:
    import uvicorn

    from service.api.app import create_app
    from service.calibration_service import CalibrationService
    from service.cli import connection_guard, exposure, repeat_limiter
    from service.cli.server import ServiceServer
    from service.store.db_claim import DatabaseClaim
    from service.store.engines import database_claim

    settings = settings_from(args)
    # plain HTTP beyond loopback refused without --insecure, TLS files checked: before anything is opened
    exposure_warning = exposure.check(settings.server)
    if exposure_warning:
        output.note(exposure_warning)
    # before the database is migrated or recovered: a second serve on this database ends here, in one line
    # (a flock on a SQLite file; on a shared server the lab's bench claim, taken at start, rules)
    claim: DatabaseClaim | None = database_claim(settings.server.db_path, settings.server.port)
    try:
        claim.acquire()  # DatabaseInUse (a StorageError) names the holder: one line, exit 2
    except OSError:
        claim = None  # no file can be made there: opening the database names why
    try:
        service = CalibrationService(settings, storage=open_database(settings), claim=claim)
        # the bench's name in a lab's database (service/runs/lab.py): BenchInUse names the live holder, exit 2
        service.lab.claim()
    except BaseException:
        if claim is not None:
            claim.release()
        raise
    app = create_app(service)

    # connections bounded below the open files (service/cli/connection_guard.py)
    open_files = connection_guard.raise_open_files_limit()
    cap = connection_guard.connection_cap(settings.server.max_connections, open_files)
    if cap < settings.server.max_connections:
        output.note(
            f"ripplecal: at most {cap} connections (server.max_connections {settings.server.max_connections}): "
            f"this process may open {open_files} files (raise `ulimit -n` for more)"
        )
    guard = connection_guard.ConnectionGuard(cap, settings.server.request_head_timeout_s)
    try:
        listeners = connection_guard.listening_sockets(settings.server.host, settings.server.port, guard)
    except StartError:
        service.stop()  # made, not started: frees what it holds (the database claim, the bench's name)
        raise
    output.serving(
        __version__, settings.server.host, settings.server.port, "https" if settings.server.ssl_certfile else "http"
    )
    # signals stop it bench safe, a second one forced, within bounds (service/cli/server.py);
    # timeout_graceful_shutdown: a backstop for a connection that does not end by itself
    server = ServiceServer(
        uvicorn.Config(
            app,
            host=settings.server.host,
            port=settings.server.port,
            log_level="info",
            timeout_graceful_shutdown=10,
            http=connection_guard.guarded_h11_protocol(guard),
            timeout_keep_alive=settings.server.keep_alive_timeout_s,
            backlog=connection_guard.accept_batch(cap),
            ssl_certfile=settings.server.ssl_certfile,
            ssl_keyfile=settings.server.ssl_keyfile,
        ),
        service,
    )
    logging.getLogger("uvicorn.access").addFilter(_path_without_query)  # after uvicorn's logging config
    limiters = repeat_limiter.install()  # after uvicorn's logging config too: on its handlers and the root's
    try:
        server.run(sockets=listeners)
    except KeyboardInterrupt:
        # uvicorn re-raises the Ctrl+C it handled once the shutdown is done: exit as interrupted, quietly
        return 130
    finally:
        for limiter in limiters:
            limiter.close()  # the summaries still held back
    # a Ctrl+C whose re-raise did nothing: SIGINT ignored since the start (a background job of a shell without
    # job control inherits SIG_IGN; uvicorn handled it all the same): interrupted, as with the handler in place
    return 130 if server.signals and server.signals[0] == signal.SIGINT else 0


def _path_without_query(record: logging.LogRecord) -> bool:
    """uvicorn's access log line without the query string: a token a client puts in a query is not logged.
    Its args are (client, method, path with query, HTTP version, status)."""
    if isinstance(record.args, tuple) and len(record.args) == 5 and isinstance(record.args[2], str):
        client, method, path, version, status = record.args
        record.args = (client, method, path.split("?", 1)[0], version, status)
    return True


def cmd_bench_check(args) -> int:
    """The bring-up check (service/bench/bringup.py): one line per check on stdout; 0 only when every one passed."""
    from service.calibration_service import CalibrationService

    settings = settings_from(args)
    storage = open_database(settings)
    output.starting_bench(args.bench)
    with CalibrationService(settings, storage=storage) as service:
        report = service.bench_check(spin=args.spin)
    if args.json:
        print(json.dumps(report, indent=1))
    else:
        for c in report["checks"]:
            mark = "ok  " if c["ok"] else "FAIL"
            print(f"{mark} {c['name']}: {c['detail']}" + ("" if c["ok"] or not c["fix"] else f"\n     fix: {c['fix']}"))
        print("all checks passed" if report["ok"] else "some checks failed: fix them before a run")
    return 0 if report["ok"] else 1


def cmd_identify(args) -> int:
    """One operating point; its states and accepted windows on stderr as the engine publishes them."""
    from service.api.public.results import result_public
    from service.calibration_service import CalibrationService
    from service.model.operating_point import OperatingPoint
    from service.runs.identify import parse_options

    settings = settings_from(args)
    op = OperatingPoint(torque_nm=args.torque, speed_rpm=args.speed, udc_v=args.udc)
    options = parse_options(args.method, json_option(args.options))
    storage = open_database(settings)
    output.starting_bench(args.bench)
    with CalibrationService(settings, storage=storage) as service:
        progress = output.JobProgress()

        def finished(job_id: int) -> dict | None:
            job = service.records.get_job(job_id)
            return job if job["state"] in JOB_FINAL else None

        job_id = None

        def submit() -> int:
            nonlocal job_id
            job_id = progress.queued(service.engine.submit_identification(op, args.method, options))
            return job_id

        job = follow(
            service,
            submit,
            finished,
            timeout_s=args.timeout,
            interval_s=1.0,
            on_event=progress.event,
            timeout_message=lambda j: (
                f"identification job {j} did not finish within {args.timeout:g} s (--timeout); it was cancelled"
            ),
        )
        result = result_public(service.records.get_result(job["result_id"])).model_dump() if job["result_id"] else None
    output.identification(op, job_id, job, result, display_location(settings.server.db_path), args.json)
    return 0 if job["state"] == "done" else 1


def cmd_sweep(args) -> int:
    """A grid; its progress on stderr each time a point is done or its state changes."""
    from service.calibration_service import CalibrationService
    from service.runs.identify import parse_options
    from service.runs.plans import Grid

    settings = settings_from(args)
    grid = Grid(torque_nm=args.torque, speed_rpm=args.speed, udc_v=args.udc)
    options = parse_options(args.method, json_option(args.options))
    storage = open_database(settings)
    started = time.monotonic()
    with CalibrationService(settings, storage=storage) as service:
        progress = output.SweepProgress()

        def finished(sweep_id: int) -> dict | None:
            s = service.seen_sweep(sweep_id)
            progress.show(sweep_id, s)
            return s if s["state"] in JOB_FINAL else None

        sweep_id = None

        def submit() -> int:
            nonlocal sweep_id
            sweep_id = service.engine.submit_sweep(grid, args.method, options)
            return sweep_id

        sweep = follow(
            service,
            submit,
            finished,
            timeout_s=args.timeout,
            interval_s=0.05,
            timeout_message=lambda s: f"sweep {s} did not finish before the timeout",
        )
    output.sweep_outcome(sweep_id, sweep, time.monotonic() - started, args.json)
    return 0 if sweep["state"] == "done" and sweep["failed_points"] == 0 else 1


def cmd_export(args) -> int:
    from service.api.public.maps import map_public
    from service.maps.lut_export import export_map

    settings = settings_from(args)
    m = map_public(open_database(settings), args.map_id)
    if m is None:
        output.note(f"map {args.map_id} does not exist in {display_location(settings.server.db_path)}")
        return 2
    text = export_map(m.model_dump(), args.format)
    if args.out:
        Path(args.out).write_text(text)
        output.line(f"wrote {args.out}")
    else:
        sys.stdout.write(text)
    return 0


def cmd_token(args) -> int:
    storage = storage_from(args)
    if args.token_cmd == "create":
        token_id, token = storage.create_token(args.role, args.label or "")
        output.token_created(token_id, args.role, token)
    elif args.token_cmd == "revoke":
        if not storage.revoke_token(args.token_id):
            output.note(f"token {args.token_id} does not exist or is already revoked")
            return 1
        output.line(f"token {args.token_id} revoked")
    else:
        output.tokens(storage.list_tokens())
    return 0


def cmd_schedule(args) -> int:
    """Schedules live in the database: a running `serve` on the same --db picks up a new one on its
    next pass (schedules.tick_s), as it reads tokens made by `token create`."""
    from pydantic import TypeAdapter

    from service.api.public.schedules import schedule_public
    from service.api.schemas import SweepCreate
    from service.runs.schedules import (
        check_cron,
        check_timezone,
        create_schedule,
        delete_schedule,
        iso,
        next_runs,
        utc_now,
    )

    settings = settings_from(args)
    if args.schedule_cmd == "preview":
        cron, zone = check_cron(args.cron), check_timezone(args.timezone)
        start = datetime.fromisoformat(args.start) if args.start else utc_now()
        for t in next_runs(cron, zone, start, args.count):
            output.line(iso(t))
        return 0
    storage = open_database(settings)
    now = utc_now()
    if args.schedule_cmd == "add":
        # a refusal (ValidationError, LimitError) is said by main, one line per field at fault
        sweep = TypeAdapter(SweepCreate).validate_python(
            {
                "grid": {"torque_nm": args.torque, "speed_rpm": args.speed, "udc_v": args.udc},
                "method": args.method,
                "options": json.loads(args.options) if args.options else {},
                "confirm_large": args.confirm_large,
            }
        )
        schedule_id = create_schedule(
            storage, settings, now, args.name, args.cron, args.timezone, sweep, enabled=not args.disabled
        )
        output.schedule_added(
            schedule_public(storage, storage.get_schedule(schedule_id), now), display_location(settings.server.db_path)
        )
    elif args.schedule_cmd == "rm":
        try:
            delete_schedule(storage, now, args.schedule_id)
        except KeyError:
            output.note(f"schedule {args.schedule_id} does not exist in {display_location(settings.server.db_path)}")
            return 1
        output.line(f"schedule {args.schedule_id} deleted")
    else:
        rows = storage.list_schedules()
        if args.json:
            output.as_json([schedule_public(storage, r, now).model_dump() for r in rows])
            return 0
        output.schedules(
            [schedule_public(storage, r, now, next_count=1, run_count=1) for r in rows],
            display_location(settings.server.db_path),
        )
    return 0


def cmd_maps(args) -> int:
    if args.maps_cmd == "download":
        return _download_map(args)
    from service.api.public.maps import map_public

    storage = storage_from(args)
    maps = [map_public(storage, row["id"]) for row in storage.list_maps(args.limit)]
    if args.json:
        output.as_json([m.model_dump(exclude={"cells"}) for m in maps])
        return 0
    output.maps(maps)
    return 0


def _download_map(args) -> int:
    """The map's LUT into the drive over the bench, as POST /maps/{id}/download does (same rules: no ok
    cell is refused, a map with cells that would inject nothing under the chosen fill needs --force;
    --no-fill leaves the filled cells out, --interpolation names the drive's mode). It opens the bench itself: run it with no
    `ripplecal serve` using the same bench (two masters on one bus and one DAQ port would fight over
    it); without --bench it downloads into an emulator of its own."""
    from service.bench.errors import BenchError
    from service.calibration_service import CalibrationService
    from service.runs import lut_download

    settings = settings_from(args)
    storage = open_database(settings)
    try:  # refused before the bench is started
        lut = lut_download.prepare(storage, args.map_id, args.force, fill=args.fill, interpolation=args.interpolation)
    except lut_download.MapNotFound as exc:
        output.error(f"{exc} in {display_location(settings.server.db_path)}")
        return 2
    except (lut_download.LutRefused, lut_download.PartialMap) as exc:
        output.error(str(exc))
        return 2
    output.starting_bench(args.bench)
    with CalibrationService(settings, storage=storage) as service:
        try:
            receipt = lut_download.send(service.bench, lut)
        except BenchError as exc:
            output.error(str(exc))
            return 1
        except Exception as exc:  # SDO abort / timeout: the drive refused or did not answer
            output.error(f"drive refused the LUT: {exc}")
            return 1
        identity = service.bench.identity
    # without --bench the LUT went into an emulator of this command's own, gone with it: say so, never the name of
    # a bench (a `serve` elsewhere may hold another map in its emulated drive)
    throwaway = args.bench is None
    if args.json:
        output.as_json(
            {**receipt.model_dump(), **lut.receipt_fields(), "bench": identity, "throwaway_emulator": throwaway}
        )
    else:
        output.lut_downloaded(receipt, lut, identity, throwaway)
    return 0


def cmd_sweeps(args) -> int:
    from service.api.public.sweeps import sweep_public

    storage = storage_from(args)
    if args.sweeps_cmd == "show":
        row = storage.get_sweep(args.sweep_id)
        if row is None:
            output.error(f"sweep {args.sweep_id} does not exist in {storage.location}")
            return 2
        sw = sweep_public(storage, row, with_points=True)
        if args.json:
            output.as_json(sw.model_dump())
            return 0
        output.sweep_details(sw)
        return 0
    sweeps = [sweep_public(storage, row) for row in storage.list_sweeps(args.limit)]
    if args.json:
        output.as_json([sw.model_dump() for sw in sweeps])
        return 0
    output.sweeps(sweeps)
    return 0


def cmd_paper(args) -> int:
    """The paper's Fig. 8-12 on emulated benches of its own (service/paper); never a real bench."""
    from service.paper.report import run

    command = "ripplecal paper --out " + args.out + (" --quick" if args.quick else "")
    output.paper_started(args.out)
    results = run(args.out, quick=args.quick, command=command)
    output.paper(results, args.out)
    return 0
