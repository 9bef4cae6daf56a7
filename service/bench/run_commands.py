"""The one way down from a run to the hardware: every setpoint a run sends goes through `RunCommands`.

A run (service/bench/run.py) and its measurement sessions (service/bench/measurement.py) hold one
`RunCommands`, made by the run lifecycle when the run opens (service/bench/lifecycle.py). It owns, for
that run, what the drive, the load machine and the DC supply were last told: theta (manual mode),
injection mode, torque, speed and the DC link, each None while unknown (a write refused or lost leaves
it so, and the next move writes it again). Before anything is sent, each setpoint is checked:
  - against the hard limits, one value at a time (service/model/limits.py setpoint_problem: the same
    statement of each limit that refuses a request up front);
  - theta against the run's gamma_max (paper sec. 2.4: the injection's own limit; the drive clamps too);
  - against the interlocks and the run's stop (`guard`: an interlock tripped, the run's cancel token,
    the bench watchdog's stop), which also kicks the watchdog: the run's loop is alive.
Making the bench safe is not a run's command: the lifecycle's make_safe and the watchdog reach the
drivers' own safe steps directly, so they work whatever state this object is in.
"""

from __future__ import annotations

import math
import threading
import time

from drivers.dc_supply import ScpiSupply
from drivers.drive import DriveClient
from drivers.load_machine import LoadClient
from service.bench.errors import BenchError
from service.bench.faults import BenchFaults
from service.bench.trips import InterlockTripped
from service.bench.watchdog import BenchWatchdog
from service.model.limits import LimitError, check_setpoint
from service.settings import Settings

INJECTION_MODES = ("off", "manual", "lut")  # the drive's 0x2000:2 (docs/interfaces.md)
SUPPLY_TIMEOUT_S = 5.0  # the supply confirms a new voltage within this (wall clock)


class RunCommands:
    """The commands of one run (module doc). The drive, load and supply are the bench's connected drivers."""

    def __init__(
        self,
        settings: Settings,
        drive: DriveClient,
        load: LoadClient,
        supply: ScpiSupply,
        faults: BenchFaults,
        watchdog: BenchWatchdog,
        gamma_max_rad: float,
        cancel: threading.Event | None,
    ):
        self.settings = settings
        self._drive = drive
        self._load = load
        self._supply = supply
        self._faults = faults
        self._watchdog = watchdog
        self.gamma_max_rad = gamma_max_rad
        self.cancel = cancel
        # what the hardware was last told during this run (None: unknown, written again by the next move)
        self.theta: tuple[float, float] | None = None
        # the further orders last sent with theta ((order, theta_cos, theta_sin), ...; None: unknown)
        self.further: tuple[tuple[int, float, float], ...] | None = ()
        self.mode: str | None = None
        self.torque_nm: float | None = None
        self.speed_rpm: float | None = None
        self.udc_v: float | None = None
        self.drive_enabled = False  # enabled at least once in this run (its torque may be on)

    # --- the run's stop ----------------------------------------------------------------------------------
    def guard(self) -> None:
        """Checked before every command and every DAQ read of the run: kicks the watchdog; raises to stop the
        run (interlock trip, the run's cancel token, the watchdog's stop)."""
        self._watchdog.kick()
        self._faults.guard(self.cancel)
        stopped = self._watchdog.tripped
        if stopped is not None:
            raise InterlockTripped(stopped)

    def forget(self) -> None:
        """At a run's first move and after an error: nothing the hardware applies is known (the move writes it
        all again)."""
        self.theta = self.mode = None
        self.further = None
        self.torque_nm = self.speed_rpm = self.udc_v = None

    # --- the DC link -------------------------------------------------------------------------------------
    def set_dc_link(self, udc_v: float) -> None:
        """The supply to udc_v and confirmed (torque off first if any was commanded: no torque while U_dc
        changes); the supply interlock watches the new band from then on."""
        check_setpoint("udc_v", udc_v, self.settings)
        self.guard()
        if self.drive_enabled and self.torque_nm != 0.0:  # None: unknown after an error, so off too
            self.set_torque_nm(0.0)
        interlock = self._faults.supply_interlock
        self.udc_v = None
        if interlock is not None:
            interlock.expected_v = None  # not out of range while it changes
        self._supply.set_voltage(udc_v)
        self._supply.output(True)
        self._wait_supply(udc_v)
        if interlock is not None:
            interlock.expected_v = udc_v
        self.udc_v = udc_v

    def _wait_supply(self, udc_v: float) -> None:
        deadline = time.monotonic() + SUPPLY_TIMEOUT_S
        while True:
            self._watchdog.kick()  # waiting on the supply is the run's loop at work
            measured = self._supply.measure_voltage()
            if abs(measured - udc_v) <= max(0.02 * udc_v, 0.05):
                return
            if time.monotonic() > deadline:
                raise BenchError(
                    f"DC supply did not reach {udc_v:g} V within {SUPPLY_TIMEOUT_S:g} s (measures {measured:g} V)"
                )
            time.sleep(0.02)

    # --- the load machine --------------------------------------------------------------------------------
    def enable_load(self) -> None:
        """The load machine to OPERATION ENABLED (its speed loop holds the shaft from the next speed setpoint)."""
        self.guard()
        self._load.enable()

    def set_speed_rpm(self, speed_rpm: float) -> None:
        """The load machine's speed setpoint (it ramps and holds it on its own speed loop)."""
        check_setpoint("speed_rpm", speed_rpm, self.settings)
        self.guard()
        self.speed_rpm = None
        self._load.set_speed_rpm(speed_rpm)
        self.speed_rpm = speed_rpm

    def set_ramp_rpm_per_s(self, rate_rpm_per_s: float) -> None:
        """The load's ramp rate for the speed setpoints that follow (a run-up's; CiA 402 profile acceleration
        and deceleration). A stop still brakes at the load's full rate (drivers/load_machine.py)."""
        if not (math.isfinite(rate_rpm_per_s) and rate_rpm_per_s > 0):
            raise LimitError(
                f"ramp rate {rate_rpm_per_s!r} rpm/s is not a positive number",
                (("rate_rpm_per_s", "not a positive number"),),
            )
        self.guard()
        self._load.set_ramp_rpm_per_s(rate_rpm_per_s)

    def restore_full_ramp(self) -> None:
        """The load's ramp back to its full rate (after a run-up's ramps)."""
        self.guard()
        self._load.restore_full_ramp()

    # --- the drive ---------------------------------------------------------------------------------------
    def enable_drive(self) -> None:
        """The drive to OPERATION ENABLED with the run's gamma_max (no setpoint: it only clamps |theta|)."""
        self.guard()
        self._drive.enable()
        self.drive_enabled = True
        self._drive.set_gamma_max_rad(self.gamma_max_rad)

    def configure_injection(self, harmonic_order: int, decoupling: bool) -> None:
        """The injection's harmonic order and the drive's decoupling for the run (each one setpoint)."""
        self.guard()
        self._drive.set_harmonic_order(harmonic_order)
        self._drive.set_decoupling(decoupling)

    def set_torque_nm(self, torque_nm: float) -> None:
        """The drive's target torque (one setpoint: its sync toggle marks the sample from which every setpoint
        written before it is in force)."""
        check_setpoint("torque_nm", torque_nm, self.settings)
        self.guard()
        self.torque_nm = None
        self._drive.set_torque_nm(torque_nm)
        self.torque_nm = torque_nm

    def send_theta(
        self, theta_cos_rad: float, theta_sin_rad: float, further: tuple[tuple[int, float, float], ...] = ()
    ) -> None:
        """Theta to the drive (manual mode; one setpoint), with the further orders `further` ((order,
        theta_cos, theta_sin), 0x2002) applied by the same commit; refuses, before anything is sent, a sum of
        the orders' gamma above the run's gamma_max (the drive would scale them all down)."""
        gammas = [math.hypot(theta_cos_rad, theta_sin_rad)] + [math.hypot(c, s) for _, c, s in further]
        gamma_rad = sum(gammas)
        if not math.isfinite(gamma_rad):
            raise LimitError(f"theta ({theta_cos_rad}, {theta_sin_rad}) {list(further) or ''} is not finite")
        if gamma_rad > self.gamma_max_rad * (1 + 1e-9):
            what = "gamma" if not further else "the orders' gamma summed"
            raise LimitError(
                f"{what} {math.degrees(gamma_rad):.3f} deg exceeds the run's gamma_max of "
                f"{math.degrees(self.gamma_max_rad):.3f} deg"
            )
        self.guard()
        self.theta = None  # unknown until written: a refused or lost write leaves it so
        self.further = None
        self._drive.set_injection(theta_cos_rad, theta_sin_rad, further)
        self.theta = (float(theta_cos_rad), float(theta_sin_rad))
        self.further = tuple(further)

    def send_injection_mode(self, mode: str) -> None:
        """The drive's injection mode (off / manual / lut; one setpoint); make_safe sets it off again."""
        if mode not in INJECTION_MODES:
            raise LimitError(f"injection mode {mode!r} is none of {', '.join(INJECTION_MODES)}")
        self.guard()
        self.mode = None
        self._drive.set_injection_mode(mode)
        self.mode = mode

    # --- what the drive reports --------------------------------------------------------------------------
    def torque_actual_nm(self) -> float:
        """The drive's torque actual (0x6077, its estimate from nominal parameters), read now by SDO."""
        return self._drive.torque_actual_nm()
