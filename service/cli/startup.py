"""What every command resolves once at start: its settings and its database (one line if unusable)."""

from __future__ import annotations

import json
import os
import sqlite3
from pathlib import Path

from service.cli import output
from service.settings import Settings, SettingsError, load_settings
from service.store.storage import Storage, StorageError


class StartError(Exception):
    """An operator error at start (a database or bench file that cannot be used): one line naming the
    file and what is wrong, exit code 2."""


def settings_from(args) -> Settings:
    path = args.bench or getattr(args, "settings", None)
    overrides = {"server.db_path": getattr(args, "db", None)}
    if getattr(args, "bench", None):
        overrides["bench_mode"] = "bench"
    elif getattr(args, "emulate", False) or hasattr(args, "scenario"):
        if getattr(args, "emulate", False):
            overrides["bench_mode"] = "emulate"
        overrides.update(
            {
                "emulator.scenario": getattr(args, "scenario", None),
                "emulator.seed": getattr(args, "seed", None),
                "emulator.speedup": getattr(args, "speedup", None),
            }
        )
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
    missing = [
        what
        for what, url in (
            ("DAQ port ([daq] url)", settings.daq.url),
            ("DC supply port ([supply] url)", settings.supply.url),
        )
        if not url
    ]
    if missing:
        raise SettingsError(
            f"bench file {Path(path).absolute()} names no {' and no '.join(missing)}: a real bench "
            'needs both, e.g. [daq] url = "/dev/ttyUSB0" and [supply] url = "socket://192.168.0.20:5025"'
        )


def open_database(settings: Settings) -> Storage:
    """The command's database, opened and migrated at start, then printed (stderr: stdout stays clean for
    the token's last line, --json and exports). What makes it unusable is a StartError naming the file."""
    path = Path(settings.server.db_path)
    if path.is_dir():
        raise StartError(
            f"database {path} is a directory: --db must name a database file, e.g. {path / 'ripplecal.db'}"
        )
    if path.exists() and not os.access(path, os.R_OK | os.W_OK):
        raise StartError(f"database {path} cannot be read and written by this user: check its permissions")
    try:
        storage = Storage(path, busy_timeout_s=settings.server.db_busy_timeout_s)
    except StorageError as exc:  # a newer schema, a failed migration; locked, read-only, full
        raise StartError(str(exc)) from None
    except sqlite3.DatabaseError as exc:  # e.g. "file is not a database": a text file, another format
        raise StartError(
            f"database {path} is not a database SQLite can use ({exc}): --db must name a ripplecal "
            "database or a new file"
        ) from None
    except (FileExistsError, NotADirectoryError) as exc:
        raise StartError(f"database {path} cannot be created: {exc.filename} is a file, not a directory") from None
    except OSError as exc:
        raise StartError(
            f"database {path} cannot be created: {exc.strerror or type(exc).__name__}"
            + (f" ({exc.filename})" if exc.filename else "")
        ) from None
    output.database_opened(path)
    return storage


def storage_from(args) -> Storage:
    return open_database(settings_from(args))


def resolve_db_path(path: str) -> str:
    """Absolute once, at start: a relative --db or RIPPLECAL_SERVER__DB_PATH is taken against this working directory."""
    return str(Path(path).expanduser().absolute())


def json_option(text: str | None) -> dict:
    """--options: a JSON object (one line naming what is wrong otherwise)."""
    if not text:
        return {}
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"--options is not valid JSON ({exc.msg} at character {exc.pos}): {text!r}") from None
    if not isinstance(value, dict):
        raise ValueError(f"--options must be a JSON object, e.g. '{{\"mu_per_s\": 10}}', got {text!r}")
    return value
