"""The parser: the command table, one small function per command (each keeps its options to itself)."""

from __future__ import annotations

import argparse
import sys

from drivers.lut_image import DEFAULT_INTERPOLATION, INTERPOLATIONS
from service import __version__
from service.cli.handlers import (
    cmd_bench_check,
    cmd_export,
    cmd_identify,
    cmd_maps,
    cmd_paper,
    cmd_schedule,
    cmd_serve,
    cmd_sweep,
    cmd_sweeps,
    cmd_token,
)
from service.identification.registry import METHODS
from service.maps.lut_export import EXPORT_FORMATS


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


def _db_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--db",
        metavar="PATH",
        help="SQLite database file (default: RIPPLECAL_SERVER__DB_PATH, else ~/.local/share/ripplecal/ripplecal.db)",
    )
    p.add_argument("--settings", metavar="FILE", help="settings TOML")


def _parser_serve(sub) -> None:
    p = sub.add_parser("serve", help="run the REST API and dashboard")
    _add_bench_args(p)
    p.add_argument("--host", help="bind address (default 127.0.0.1; beyond loopback: TLS, or --insecure)")
    p.add_argument("--port", type=int, help="port (default 8000)")
    p.add_argument("--ssl-certfile", metavar="FILE", help="TLS certificate (PEM): serve HTTPS (README: TLS for a lab)")
    p.add_argument("--ssl-keyfile", metavar="FILE", help="the certificate's private key (PEM)")
    p.add_argument(
        "--insecure",
        action="store_true",
        default=None,  # not given: server.insecure of the settings
        help="allow plain HTTP on an address beyond loopback: tokens and answers cross the network in clear",
    )
    p.add_argument(
        "--bench-name",
        metavar="NAME",
        help="the bench's name in a lab's database (default: bench_name of the settings or bench file; "
        "'emulated' with --emulate)",
    )
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
    t.add_argument(
        "--confirm-large", action="store_true", help="allow a grid above safety.max_sweep_points_unconfirmed"
    )
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
    t = msub.add_parser(
        "download",
        help="the map's LUT into the drive (0x2001), CRC-32 read back; opens the bench "
        "itself: not while a `ripplecal serve` holds the same bench",
    )
    t.add_argument("map_id", type=int)
    t.add_argument(
        "--force",
        action="store_true",
        help="load a partial map (cells without an entry under the chosen fill: no injection there)",
    )
    t.add_argument(
        "--no-fill",
        dest="fill",
        action="store_false",
        help="leave the filled cells out (the drive then injects only at ok cells); default: with fill",
    )
    t.add_argument(
        "--interpolation",
        choices=list(INTERPOLATIONS),
        default=None,
        help=f"what the drive interpolates between cells (default: the map's own, else {DEFAULT_INTERPOLATION})",
    )
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


def _parser_bench(sub) -> None:
    p = sub.add_parser("bench", help="the bench itself: the bring-up check")
    bsub = p.add_subparsers(dest="bench_cmd", required=True)
    c = bsub.add_parser(
        "check",
        help="check the bench before a night: one line per check with what was found and the fix; exit 0 only "
        "when all pass",
    )
    _add_bench_args(c)
    c.add_argument(
        "--spin",
        action="store_true",
        help="turn the shaft slowly without torque for the angle, "
        "accelerometer and sync-line checks (interlocked, safe at the end)",
    )
    c.add_argument("--json", action="store_true", help="print the checks as JSON")
    c.set_defaults(func=cmd_bench_check)


def _parser_paper(sub) -> None:
    p = sub.add_parser(
        "paper", help="reproduce the paper's Fig. 8-12 on the emulated bench (report.html, results.json)"
    )
    p.add_argument("--out", default="build/paper", help="output directory (default build/paper)")
    p.add_argument("--quick", action="store_true", help="coarser grid and shorter records (the test's run)")
    p.set_defaults(func=cmd_paper, bench=None)


COMMANDS = (
    _parser_serve,
    _parser_identify,
    _parser_sweep,
    _parser_export,
    _parser_token,
    _parser_schedule,
    _parser_maps,
    _parser_sweeps,
    _parser_paper,
    _parser_bench,
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ripplecal", description=str(sys.modules[__package__].__doc__).splitlines()[0]
    )
    parser.add_argument("--version", action="version", version=f"ripplecal {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in COMMANDS:
        add(sub)
    return parser
