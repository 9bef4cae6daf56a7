"""`ripplecal` command line: serve, identify, sweep, export, token, schedule, maps, sweeps, paper.

identify, sweep and `maps download` run in this process against the bench (emulated unless --bench
names a bench settings file), through the same engine the REST API uses, and store into the database.
The database is resolved once, made absolute and printed (stderr) at start: --db, else
RIPPLECAL_SERVER__DB_PATH, else the per-user default ($XDG_DATA_HOME or ~/.local/share)/ripplecal/ripplecal.db,
the same for every command whatever the working directory.

The package: `parser` (the command table: one small function per command), `handlers` (each command
calls the service layer), `output` (every line a command prints), `waiting` (the one way a command
waits for a job or a sweep), `startup` (settings and the database, resolved once at start).
"""

from __future__ import annotations

import logging
import sys

from pydantic import ValidationError

from service.bench.errors import BenchUnreachable  # light: not the bench's drivers
from service.cli.parser import build_parser
from service.cli.startup import StartError, resolve_db_path
from service.model.limits import LimitError
from service.settings import SettingsError
from service.store.storage import StorageError
from service.validation_words import in_our_words

__all__ = ["main", "build_parser", "StartError", "resolve_db_path"]


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        return args.func(args)
    except (
        SettingsError,
        StartError,
        StorageError,
    ) as exc:  # StorageError: e.g. the database locked by another process
        print(f"ripplecal: {exc}", file=sys.stderr)
        return 2
    except ValidationError as exc:  # a value a model refused (an operating point's speed <= 0): said as ours
        for e in exc.errors():
            print(f"ripplecal: {in_our_words(dict(e), ['option', *e['loc']])}", file=sys.stderr)
        return 2
    except LimitError as exc:  # every field at fault on a line of its own, as the API's 422 lists them
        for line in [msg for _field, msg in exc.problems] or [str(exc)]:
            print(f"ripplecal: {line}", file=sys.stderr)
        return 2
    except (ValueError, TimeoutError) as exc:
        print(f"ripplecal: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # the service's context has already left the bench safe
        print("ripplecal: interrupted", file=sys.stderr)
        return 130
    except BenchUnreachable as exc:  # a real bench not reached: the run is refused at start
        print(f"ripplecal: {exc}", file=sys.stderr)
        return 2
