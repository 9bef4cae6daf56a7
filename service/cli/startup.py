"""What every command resolves once at start: its settings and its database (one line if unusable)."""

from __future__ import annotations

import json
from pathlib import Path

from service.cli import output
from service.names import check_name
from service.settings import Settings, SettingsError, load_settings
from service.store.engines import display_location, is_server_url
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
    for key in ("host", "port", "ssl_certfile", "ssl_keyfile", "insecure"):  # serve's; None: not given
        if getattr(args, key, None) is not None:
            overrides[f"server.{key}"] = getattr(args, key)
    overrides["bench_name"] = getattr(args, "bench_name", None)
    settings = load_settings(path, overrides=overrides)
    if getattr(args, "bench", None):
        _check_bench_file(args.bench, settings)
        if "bench_name" not in settings.model_fields_set:
            # a bench file without bench_name: the bench is called after its file (a valid name too)
            try:
                name = check_name(Path(args.bench).stem, "bench name")
            except ValueError as exc:
                raise SettingsError(
                    f"bench file {args.bench} sets no bench_name and its file name is no name: {exc}"
                ) from None
            settings = settings.model_copy(update={"bench_name": name})
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
    the token's last line, --json and exports). What makes it unusable is a StartError naming the file
    (or the server, without its password)."""
    path = display_location(settings.server.db_path)
    try:
        storage = Storage(
            settings.server.db_path,
            busy_timeout_s=settings.server.db_busy_timeout_s,
            statement_timeout_s=settings.server.db_statement_timeout_s,
        )
    except StorageError as exc:
        # not a database; a newer schema, a failed migration; locked, read-only, full, unreachable
        raise StartError(str(exc)) from None
    except (FileExistsError, NotADirectoryError) as exc:
        raise StartError(f"database {path} cannot be created: {exc.filename} is a file, not a directory") from None
    except OSError as exc:
        raise StartError(
            f"database {path} cannot be created: {exc.strerror or type(exc).__name__}"
            + (f" ({exc.filename})" if exc.filename else "")
        ) from None
    output.database_opened(storage.location)
    return storage


def storage_from(args) -> Storage:
    return open_database(settings_from(args))


def resolve_db_path(path: str) -> str:
    """Absolute once, at start: a relative --db or RIPPLECAL_SERVER__DB_PATH is taken against this working
    directory (a postgresql:// URL is kept as it is)."""
    if is_server_url(path):
        return path
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
