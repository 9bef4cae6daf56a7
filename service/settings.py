"""Settings: one TOML file plus environment overrides; the defaults run the emulated bench.

Environment overrides: RIPPLECAL_<SECTION>__<FIELD>=value, e.g. RIPPLECAL_CAN__CHANNEL=can1,
RIPPLECAL_SERVER__PORT=8001. Values are parsed as TOML scalars where possible ("5" -> 5).
The `motor`, `control` and `mechanics` sections are the bench's NOMINAL parameters (datasheet,
commissioning): the identification's model S_hat (eq. 14-20) is computed from them, never from the
emulator's truth.
"""

from __future__ import annotations

import os
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, model_validator
from pydantic_core import ErrorDetails

from service.names import check_name


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class CanSettings(_Section):
    interface: str = "socketcand"
    channel: str = "can0"
    host: str | None = "127.0.0.1"
    port: int | None = None
    bitrate: int | None = None
    service_node_id: int = Field(1, ge=1, le=127)
    heartbeat_period_ms: int = Field(100, ge=10, le=10_000)
    drive_node: int = Field(5, ge=1, le=127)
    load_node: int = Field(6, ge=1, le=127)
    sdo_timeout_s: float = Field(0.5, gt=0)
    options: dict[str, str | int | float | bool] = Field(
        default_factory=dict,
        description="further keyword arguments of the python-can interface (they override "
        "drivers.canopen_bus.INTERFACE_DEFAULTS, e.g. tcp_tune for socketcand)",
    )


class DaqSettings(_Section):
    url: str | None = None
    sample_rate_hz: float = Field(16_000.0, gt=0)
    accel_full_scale_rad_s2: float = Field(500.0, gt=0)
    read_timeout_s: float = Field(5.0, gt=0)
    sync_input: bool = Field(True, description="the drive's sync line is wired to the DAQ (flag bit 2)")
    no_sync_settle_s: float = Field(
        0.4, gt=0, description="without the sync line: plant time to let pass after a setpoint"
    )


class SupplySettings(_Section):
    url: str | None = None
    timeout_s: float = Field(1.0, gt=0)


class MotorSettings(_Section):
    """Nominal machine parameters (paper Table 1 bench)."""

    pole_pairs: int = Field(4, ge=1)
    r_s_ohm: float = Field(0.010, gt=0)
    l_d_h: float = Field(20e-6, gt=0)
    l_q_h: float = Field(20e-6, gt=0)
    psi_p_vs: float = Field(7.0e-3, gt=0)
    rated_torque_nm: float = Field(5.0, gt=0)
    i_max_a: float = Field(113.0, gt=0)


class ControlSettings(_Section):
    """Nominal current control: bandwidth, controller rate, total control delay (eq. 17), and the voltage margin
    of the firmware's field weakening."""

    bandwidth_hz: float = Field(160.0, gt=0)
    control_rate_hz: float = Field(16_000.0, gt=0)
    delay_periods: float = Field(1.5, ge=0)
    voltage_margin: float = Field(
        0.95,
        gt=0.5,
        le=1.0,
        description="the firmware's field weakening keeps the nominal "
        "steady |u_dq| at this fraction of U_dc/sqrt(3) (the rest is headroom for its PI); "
        "the predicted field-weakening onset of a sweep plan uses it",
    )


class MechanicsSettings(_Section):
    """G_Salpha(s): torque (Nm) -> measured angular acceleration (rad/s^2), paper sec. 2.3."""

    inertia_kg_m2: float = Field(2.0e-3, gt=0)
    zero_rad_s: float = -35954.0
    pole_re_rad_s: float = -19.6
    pole_im_rad_s: float = 6746.2


class IdentificationSettings(_Section):
    harmonic_order: int = Field(6, ge=1, le=60)
    gamma_max_deg: float = Field(15.0, gt=0, le=45)
    decoupling: bool = Field(
        False, description="run the drive with decoupling of nominal control and injection (sec. 3.1)"
    )
    s_model: Literal["auto", "paper", "closed_loop"] = Field(
        "auto",
        description="S_hat: eq. 14-20 as written (paper), with the nominal current loop closed around the "
        "machine (closed_loop), or auto: closed_loop unless the drive decouples",
    )


class SafetySettings(_Section):
    """Limits every setpoint is checked against before anything is sent (also in a sweep's dry run)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    max_torque_nm: float = Field(5.0, gt=0)
    torque_sign: Literal["both", "positive", "negative"] = Field(
        "both", description="torque directions the bench may command; zero torque is always allowed"
    )
    min_speed_rpm: float = Field(
        100.0,
        gt=0,
        description="slowest speed a run may ask for: below it a harmonic period has no useful number of samples",
    )
    max_speed_rpm: float = Field(6000.0, gt=0)
    min_udc_v: float = Field(6.0, ge=0)
    max_udc_v: float = Field(60.0, gt=0)
    max_sweep_points_unconfirmed: int = Field(400, ge=1, description="a bigger sweep needs confirm_large = true")
    # the envelope held on what the motor does (service/model/limits.py, service/bench/interlocks.py ActualsOutsideLimits)
    torque_tolerance_fraction: float = Field(
        0.2,
        gt=0,
        le=1.0,
        description="a point's torque actual may differ from its command by this fraction of the command (or "
        "torque_tolerance_nm, whichever is wider): beyond it the result is never ok, and a point the model "
        "predicts beyond it is refused up front (0x6077 is the drive's estimate from its nominal parameters)",
    )
    torque_tolerance_nm: float = Field(0.25, gt=0, description="... or this many Nm, whichever is wider")
    actuals_margin_fraction: float = Field(
        0.1,
        gt=0,
        le=1.0,
        description="the actuals interlock trips on a torque actual beyond max_torque_nm by this fraction, of "
        "the sign torque_sign forbids beyond this fraction of max_torque_nm, and on a speed actual beyond "
        "max_speed_rpm by this fraction",
    )
    current_trip_fraction: float = Field(
        1.25,
        ge=1.0,
        le=3.0,
        description="the actuals interlock trips on a current actual above this multiple of motor.i_max_a (the "
        "injection's harmonic current rides on the limit the firmware holds)",
    )
    max_plant_s_per_point: float = Field(
        600.0,
        gt=0,
        le=86_400,
        description="most plant time a method's options may "
        "ask for at one operating point (their worst case, checked before queueing)",
    )

    @model_validator(mode="after")
    def _ordered(self):
        if self.min_speed_rpm >= self.max_speed_rpm:
            raise ValueError(f"min_speed_rpm {self.min_speed_rpm:g} must be below max_speed_rpm {self.max_speed_rpm:g}")
        if self.min_udc_v > self.max_udc_v:
            raise ValueError(f"min_udc_v {self.min_udc_v:g} must not exceed max_udc_v {self.max_udc_v:g}")
        return self


class InterlockSettings(_Section):
    """Interlocks: how they are watched, and whether a drive fault may ever be reset without a person."""

    monitor_period_s: float = Field(0.05, gt=0, le=1.0, description="period of the interlock monitor thread")
    stall_s: float = Field(
        1.0,
        gt=0,
        description="a monitor gap this long trips the run: twice the drive's 500 ms "
        "heartbeat consumer time, so the drive has surely lost our heartbeat (a shorter gap that "
        "the drive noticed trips through its EMCY; one it did not notice harms no measurement)",
    )
    supply_tolerance_fraction: float = Field(
        0.1, gt=0, le=1.0, description="supply trips outside +-this fraction of its setpoint"
    )
    supply_tolerance_v: float = Field(0.5, gt=0, description="... or outside +-this many volts, whichever is wider")
    auto_fault_reset: bool = Field(
        False, description="reset a drive/load FAULT without a person (off: POST /bench/fault-reset)"
    )
    auto_fault_reset_per_hour: int = Field(2, ge=0, le=60, description="at most this many automatic resets per hour")
    watchdog_s: float = Field(
        3.0,
        gt=0,
        le=60,
        description="the bench watchdog disables drive and load when a run's loop has not reported for this "
        "long (wall time): a worker stuck (e.g. on a database that hangs) never holds the bench at torque",
    )


class EngineSettings(_Section):
    auto_resume: bool = Field(False, description="on start, resume sweeps a previous service run left interrupted")


class SchedulesSettings(_Section):
    missed_grace_s: float = Field(
        3600.0,
        ge=0,
        le=7 * 86_400,
        description="a firing missed while the service was "
        "down still runs once at start if it fell due at most this long ago; older: recorded as missed",
    )
    tick_s: float = Field(1.0, gt=0, le=60, description="how often the scheduler looks for due firings")


class RecordingsSettings(_Section):
    """Raw recordings of every identification (MF4, service/store/recordings/) and their retention."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    enabled: bool = Field(True, description="keep the raw DAQ samples and theta setpoints of every identification")
    directory: str | None = Field(
        None, description="where the MF4 files go (default: 'recordings' next to the database)"
    )
    keep_gb: float = Field(
        20.0,
        gt=0,
        description="keep the newest recordings up to this many GB (1e9 bytes); "
        "older ones are deleted after each write (the newest one is always kept)",
    )


class EmulatorSettings(_Section):
    scenario: str = "paper-bench"
    seed: int | None = None
    speedup: float = Field(
        1.0,
        ge=0,
        le=1000,
        description="1: the emulator streams in real time, as a real bench "
        "(what a bench pays is measured there); 0: as fast as the DAQ is read (simulation)",
    )
    start_timeout_s: float = Field(60.0, gt=0)


def default_db_path() -> str:
    """One database per user whatever the working directory (XDG data dir), so `ripplecal token create`
    run anywhere lands in the database `ripplecal serve` reads. RIPPLECAL_SERVER__DB_PATH or --db
    name another; the CLI makes a relative one absolute (against its working directory) once, at start."""
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return str(Path(base) / "ripplecal" / "ripplecal.db")


class ServerSettings(_Section):
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=1, le=65535)
    db_path: str = Field(default_factory=default_db_path)
    max_body_bytes: int = Field(
        1_048_576, ge=1024, description="larger request bodies get 413 before they are parsed or authenticated"
    )
    db_busy_timeout_s: float = Field(
        10.0,
        gt=0,
        le=600,
        description="how long a database access waits for another "
        "process's lock before the service treats the database as unavailable (a sweep "
        "then waits with the bench safe, the API answers 503)",
    )
    db_statement_timeout_s: float = Field(
        5.0,
        gt=0,
        le=600,
        description="how long one database statement may take (PostgreSQL statement_timeout, and the "
        "client's own bound on an answer from a server or session that hangs) before the service treats "
        "the database as unavailable",
    )
    # TLS and exposure: a bind beyond loopback carries bearer tokens over the lab network
    ssl_certfile: str | None = Field(
        None, description="TLS certificate chain (PEM): with it the API is served over HTTPS"
    )
    ssl_keyfile: str | None = Field(
        None, description="the certificate's private key (PEM), unless ssl_certfile holds it"
    )
    insecure: bool = Field(
        False,
        description="serve plain HTTP on an address beyond loopback (tokens and answers cross the network in clear)",
    )
    # connections: a flood of idle ones must not use up the process's open files
    max_connections: int = Field(
        512,
        ge=4,
        le=100_000,
        description="open HTTP connections at most (lowered to half the process's open-file limit); at the cap a new "
        "connection closes the longest-idle one, or gets 503 when every one is in a request",
    )
    request_head_timeout_s: float = Field(
        10.0, gt=0, le=300, description="a connection that sends no complete request head within this is closed"
    )
    keep_alive_timeout_s: int = Field(5, ge=1, le=300, description="an idle keep-alive connection is closed after this")
    # authentication: wrong tokens are throttled per client address
    auth_max_failures: int = Field(
        10, ge=1, description="wrong tokens one client address may send within auth_failure_window_s; then 429"
    )
    auth_failure_window_s: float = Field(60.0, gt=0, le=86_400, description="the window auth_max_failures counts in")


class Settings(_Section):
    bench_mode: Literal["emulate", "bench"] = "emulate"
    # the bench's name in a lab's database: printable text, as every name (service/names.py)
    bench_name: Annotated[str, AfterValidator(lambda v: check_name(v, "bench name"))] = "emulated"
    can: CanSettings = CanSettings()
    daq: DaqSettings = DaqSettings()
    supply: SupplySettings = SupplySettings()
    motor: MotorSettings = MotorSettings()
    control: ControlSettings = ControlSettings()
    mechanics: MechanicsSettings = MechanicsSettings()
    identification: IdentificationSettings = IdentificationSettings()
    safety: SafetySettings = SafetySettings()
    interlocks: InterlockSettings = InterlockSettings()
    engine: EngineSettings = EngineSettings()
    schedules: SchedulesSettings = SchedulesSettings()
    recordings: RecordingsSettings = RecordingsSettings()
    emulator: EmulatorSettings = EmulatorSettings()
    server: ServerSettings = Field(default_factory=ServerSettings)  # the db default read when loaded, not at import


class SettingsError(ValueError):
    """A settings file or override that cannot be used; the message says which key and why."""


ENV_PREFIX = "RIPPLECAL_"


def _parse_env_value(text: str) -> Any:
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def load_settings(
    path: str | Path | None = None, environ: dict[str, str] | None = None, overrides: dict[str, Any] | None = None
) -> Settings:
    """Settings from defaults <- TOML file <- environment <- explicit overrides (CLI flags). A problem is
    a SettingsError of one line naming the file (or the environment variable, or the command line) and
    the key."""
    data: dict[str, Any] = {}
    p = Path(path) if path is not None else None
    if p is not None:
        try:
            data = tomllib.loads(p.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise SettingsError(f"settings file {p} does not exist") from None
        except IsADirectoryError:
            raise SettingsError(f"settings file {p} is a directory, not a TOML file") from None
        except UnicodeDecodeError as exc:
            raise SettingsError(f"settings file {p} is not UTF-8 text (byte {exc.start}): is it a TOML file?") from None
        except OSError as exc:
            raise SettingsError(f"settings file {p} cannot be read ({exc.strerror or type(exc).__name__})") from None
        except tomllib.TOMLDecodeError as exc:
            raise SettingsError(f"settings file {p} is not valid TOML: {exc}") from None
    sources: dict[tuple[str, ...], str] = {}  # key path -> where it came from, if not from the file
    env = os.environ if environ is None else environ
    for key, raw in env.items():
        if not key.startswith(ENV_PREFIX):
            continue
        parts = key[len(ENV_PREFIX) :].lower().split("__")
        _put(data, parts, _parse_env_value(raw), f"environment {key}", p)
        sources[tuple(parts)] = f"environment {key}"
    for dotted, value in (overrides or {}).items():
        if value is None:
            continue
        parts = dotted.split(".")
        _put(data, parts, value, "the command line", p)
        sources[tuple(parts)] = "the command line"
    try:
        return Settings.model_validate(data)
    except ValidationError as exc:
        problems = "; ".join(_problem(e, sources) for e in exc.errors())
        where = f"settings file {p}" if p is not None else "invalid settings"
        raise SettingsError(f"{where}: {problems}") from None


def _put(data: dict[str, Any], parts: list[str], value: Any, source: str, path: Path | None) -> None:
    node = data
    for part in parts[:-1]:
        node = node.setdefault(part, {})
        if not isinstance(node, dict):
            where = f"settings file {path}" if path is not None else "settings"
            raise SettingsError(f"{where}: {part} is not a table, so {source} cannot set {'.'.join(parts)}")
    node[parts[-1]] = value


def _problem(error: ErrorDetails, sources: dict[tuple[str, ...], str]) -> str:
    """'key: what is wrong', with where the key came from when that is not the file."""
    loc = tuple(str(x) for x in error["loc"])
    msg = "unknown key" if error["type"] == "extra_forbidden" else error["msg"].removeprefix("Value error, ")
    source = next((sources[loc[:n]] for n in range(len(loc), 0, -1) if loc[:n] in sources), None)
    return f"{'.'.join(loc)}: {msg}" + (f" (set by {source})" if source else "")
