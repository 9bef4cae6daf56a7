"""The contracts between the bench's parts: what a collaborator that is passed in must provide.

- `DriveCommands`: what a measurement session (service/bench/measurement.py) may send to the drive
  while it measures; the run's commands (`RunCommands`, service/bench/run_commands.py: the one way down)
  provide it, checking every value on the way.
- `RunBench`: what a run (service/bench/run.py) needs from the bench that opened it; the `Bench`
  facade (service/bench/bench.py) provides it.
- `Guard`: called before every DAQ read of a run; raises to stop it (cancel token, interlock trip).
- `Recorder`: a raw recording a point's stream and session feed while one is set (the store's
  `RunRecorder`, service/store/recordings.py, set by the run layer: the bench never imports the store).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable, Protocol

if TYPE_CHECKING:
    from drivers.daq_protocol import DecodedSamples
    from service.bench.interlock_monitor import InterlockMonitor
    from service.bench.interlocks import ActualsOutsideLimits, SupplyOutOfRange
    from service.bench.live_values import LiveValues
    from service.bench.setpoint_accounting import SetpointAccounting
    from service.model.demodulation import ResonanceTracker
    from service.settings import Settings

Guard = Callable[[], None]


class DriveCommands(Protocol):
    """What a session may send to the drive while it measures (the bench checks every value)."""

    def send_theta(
        self, theta_cos_rad: float, theta_sin_rad: float, further: tuple[tuple[int, float, float], ...] = ()
    ) -> None: ...

    def send_injection_mode(self, mode: str) -> None: ...


class Recorder(Protocol):
    """A raw recording: every sample a point's stream consumes, and each theta setpoint with its effect."""

    def samples(self, s: DecodedSamples, counted: bool) -> None: ...

    def setpoint(self, effect_index: int, theta_cos_rad: float, theta_sin_rad: float) -> None: ...


class RunBench(Protocol):
    """What a run needs from the bench that opened it: the settings, the setpoint accounting and the
    interlocks it is watched by, the shaft mode its sessions learn and the live view its sessions publish
    to. Its commands to the hardware are not here: they go through the run's RunCommands only."""

    @property
    def settings(self) -> Settings: ...

    @property
    def accounting(self) -> SetpointAccounting: ...

    @property
    def interlocks(self) -> InterlockMonitor: ...

    @property
    def supply_interlock(self) -> SupplyOutOfRange: ...

    @property
    def actuals(self) -> ActualsOutsideLimits:
        """The drive's actuals held against the limits (pushed from its TPDO); a point's mean torque actual."""

    @property
    def resonance(self) -> ResonanceTracker: ...

    @property
    def live(self) -> LiveValues: ...
