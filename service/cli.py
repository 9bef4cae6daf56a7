"""`ripplecal` command line: serve, identify, sweep, export, token.

identify and sweep run in this process against the bench (emulated unless --bench names a bench
settings file), through the same engine the REST API uses, and store their results in --db.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

from service import __version__
from service.identification.registry import METHODS
from service.lut_export import EXPORT_FORMATS
from service.settings import Settings, SettingsError, load_settings


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
        overrides["bench_name"] = Path(args.bench).stem
    elif getattr(args, "emulate", False) or hasattr(args, "scenario"):
        if getattr(args, "emulate", False):
            overrides["bench_mode"] = "emulate"
        overrides.update({"emulator.scenario": getattr(args, "scenario", None), "emulator.seed": getattr(args, "seed", None),
                          "emulator.speedup": getattr(args, "speedup", None)})
    for key in ("host", "port"):
        if getattr(args, key, None) is not None:
            overrides[f"server.{key}"] = getattr(args, key)
    return load_settings(path, overrides=overrides)


def cmd_serve(args) -> int:
    import signal

    import uvicorn

    from service.api.app import create_app
    from service.calibration_service import CalibrationService
    settings = _settings(args)
    service = CalibrationService(settings)
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
    try:
        server.run()
    except KeyboardInterrupt:
        # uvicorn re-raises the Ctrl+C it handled once the shutdown is done: exit as interrupted, quietly
        return 130
    return 0




def _wait(predicate, deadline: float, what: str):
    while time.monotonic() < deadline:
        value = predicate()
        if value is not None:
            return value
        time.sleep(0.05)
    raise TimeoutError(f"{what} did not finish before the timeout")


def cmd_identify(args) -> int:
    from service.calibration_service import CalibrationService
    from service.identify import parse_options
    from service.public import result_public
    from service.operating_point import OperatingPoint
    settings = _settings(args)
    op = OperatingPoint(torque_nm=args.torque, speed_rpm=args.speed, udc_v=args.udc)
    options = parse_options(args.method, json.loads(args.options) if args.options else {})
    with CalibrationService(settings) as service:
        job_id = service.engine.submit_identification(op, args.method, options)
        job = _wait(lambda: (j if (j := service.storage.get_job(job_id))["state"] in ("done", "failed", "cancelled") else None),
                    time.monotonic() + args.timeout, f"identification job {job_id}")
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
        print(f"result id         {result['id']} in {settings.server.db_path}")
    return 0 if job["state"] == "done" else 1


def cmd_sweep(args) -> int:
    from service.calibration_service import CalibrationService
    from service.identify import parse_options
    from service.plans import Grid
    settings = _settings(args)
    grid = Grid(torque_nm=args.torque, speed_rpm=args.speed, udc_v=args.udc)
    options = parse_options(args.method, json.loads(args.options) if args.options else {})
    started = time.monotonic()
    with CalibrationService(settings) as service:
        sweep_id = service.engine.submit_sweep(grid, args.method, options)
        last = None

        def finished():
            nonlocal last
            s = service.storage.get_sweep(sweep_id)
            if (s["done_points"], s["state"]) != last:
                last = (s["done_points"], s["state"])
                print(f"sweep {sweep_id}: {s['done_points']}/{s['total_points']} points, {s['state']}", flush=True)
            return s if s["state"] in ("done", "failed", "cancelled") else None
        sweep = _wait(finished, time.monotonic() + args.timeout, f"sweep {sweep_id}")
    print(f"sweep {sweep_id} {sweep['state']} in {time.monotonic() - started:.1f} s wall; "
          f"{sweep['failed_points']} failed point(s); map {sweep['map_id']}")
    return 0 if sweep["state"] == "done" and sweep["failed_points"] == 0 else 1


def cmd_export(args) -> int:
    from service.lut_export import export_map
    from service.public import map_public
    from service.storage import Storage
    settings = _settings(args)
    m = map_public(Storage(settings.server.db_path), args.map_id)
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
    from service.storage import Storage
    storage = Storage(_settings(args).server.db_path)
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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ripplecal", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"ripplecal {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("serve", help="run the REST API and dashboard")
    _add_bench_args(p)
    p.add_argument("--host", help="bind address (default 127.0.0.1)")
    p.add_argument("--port", type=int, help="port (default 8000)")
    p.set_defaults(func=cmd_serve)

    for name, func, helptext in (("identify", cmd_identify, "identify theta* at one operating point"),
                                 ("sweep", cmd_sweep, "identify over a grid and build a map")):
        p = sub.add_parser(name, help=helptext)
        _add_bench_args(p)
        if name == "identify":
            p.add_argument("--torque", type=float, required=True, help="torque command, Nm")
            p.add_argument("--speed", type=float, required=True, help="speed, rpm")
            p.add_argument("--udc", type=float, default=12.0, help="DC-link voltage, V (default 12)")
        else:
            p.add_argument("--torque", type=_floats, required=True, help="torques, Nm, comma-separated")
            p.add_argument("--speed", type=_floats, required=True, help="speeds, rpm, comma-separated")
            p.add_argument("--udc", type=_floats, default=[12.0], help="DC-link voltages, V, comma-separated")
        p.add_argument("--method", choices=list(METHODS), default="adaptive")
        p.add_argument("--options", help="method options as JSON, e.g. '{\"mu_per_s\": 10}'")
        p.add_argument("--timeout", type=float, default=3600.0, help="give up after this many seconds")
        p.add_argument("--json", action="store_true", help="print the full result as JSON")
        p.set_defaults(func=func)

    p = sub.add_parser("export", help="export a map as a LUT")
    p.add_argument("map_id", type=int)
    p.add_argument("--format", choices=list(EXPORT_FORMATS), default="csv")
    p.add_argument("--out", help="file to write (stdout otherwise)")
    p.add_argument("--db", metavar="PATH")
    p.add_argument("--settings", metavar="FILE")
    p.set_defaults(func=cmd_export, bench=None)

    p = sub.add_parser("token", help="create, revoke or list API tokens")
    tsub = p.add_subparsers(dest="token_cmd", required=True)
    t = tsub.add_parser("create")
    t.add_argument("--role", choices=["viewer", "operator", "admin"], required=True)
    t.add_argument("--label")
    t.add_argument("--db", metavar="PATH")
    t.add_argument("--settings", metavar="FILE")
    t = tsub.add_parser("revoke")
    t.add_argument("token_id", type=int)
    t.add_argument("--db", metavar="PATH")
    t.add_argument("--settings", metavar="FILE")
    t = tsub.add_parser("list")
    t.add_argument("--db", metavar="PATH")
    t.add_argument("--settings", metavar="FILE")
    p.set_defaults(func=cmd_token, bench=None)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except SettingsError as exc:
        print(f"ripplecal: {exc}", file=sys.stderr)
        return 2
    except (ValueError, TimeoutError) as exc:
        print(f"ripplecal: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
