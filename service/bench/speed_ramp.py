"""A speed ramp inside a run: the load machine ramps from where the run stands to a new speed at a set rate
while the DAQ stream is read without a break (a run-up's raw data, service/runs/runup.py).

The run stands settled at its start point (BenchRun.operating_point). The ramp rate is the load's profile
acceleration (CiA 402 0x6083/0x6084, set through the run's commands); the speed setpoint is not a drive
setpoint (no sync toggle), so the samples are read from the command on. The ramp ends once the encoder
has shown the target speed for `HOLD_S` of plant time, or fails (MeasurementError) when the shaft does not
get there within the time the rate predicts plus a margin. Every read goes through the stream's guard
(interlocks, cancel, watchdog kick), so a ramp is stopped as any measurement is.
"""

from __future__ import annotations

import math

from drivers.daq_protocol import DecodedSamples
from service.bench.measurement import OperatingPointSession
from service.bench.run_commands import RunCommands
from service.identification.session import MeasurementError
from service.model.harmonic import mechanical_speed_rpm

BLOCK_S = 0.05  # DAQ read block (plant time) on which the ramp's progress is judged
HOLD_S = 0.2  # the target speed shown this long ends the ramp
MARGIN_S = 3.0  # beyond rate-predicted duration x MARGIN_FACTOR + MARGIN_S the ramp has failed
MARGIN_FACTOR = 1.5


def reached_rpm(target_rpm: float) -> float:
    """How close the encoder must show the target for the ramp to have arrived (rpm): 0.5 % or 5 rpm."""
    return max(5.0, 0.005 * abs(target_rpm))


def ramp_speed(
    session: OperatingPointSession,
    commands: RunCommands,
    from_rpm: float,
    to_rpm: float,
    rate_rpm_per_s: float,
    pole_pairs: int,
) -> DecodedSamples:
    """Ramp the load from `from_rpm` (where the run stands) to `to_rpm` at `rate_rpm_per_s` and return every DAQ
    sample from the command until the target has held HOLD_S (module doc)."""
    stream = session.stream
    rate_hz = stream.sample_rate_hz
    block = max(1, int(BLOCK_S * rate_hz))
    hold_blocks = max(1, math.ceil(HOLD_S / BLOCK_S))
    limit_samples = int(((abs(to_rpm - from_rpm) / rate_rpm_per_s) * MARGIN_FACTOR + MARGIN_S) * rate_hz)
    commands.set_ramp_rpm_per_s(rate_rpm_per_s)
    commands.set_speed_rpm(to_rpm)
    blocks: list[DecodedSamples] = []
    taken, held = 0, 0
    last_rpm: float | None = None
    while held < hold_blocks:
        if taken > limit_samples:
            shown = "no reading" if last_rpm is None else f"{last_rpm:.0f} rpm"
            raise MeasurementError(
                f"the load did not ramp to {to_rpm:g} rpm at {rate_rpm_per_s:g} rpm/s within "
                f"{limit_samples / rate_hz:.1f} s of plant time (the encoder shows {shown})"
            )
        samples = stream.next_exact(block)
        blocks.append(samples)
        taken += len(samples)
        try:
            last_rpm = mechanical_speed_rpm(samples.angle_rad, rate_hz, pole_pairs, samples.gap_before)
        except ValueError:  # a block of gaps: no reading, the ramp goes on
            continue
        held = held + 1 if abs(last_rpm - to_rpm) <= reached_rpm(to_rpm) else 0
    return DecodedSamples.concat(blocks)


def ramp_through(
    session: OperatingPointSession,
    commands: RunCommands,
    legs: list[tuple[float, float]],
    rate_rpm_per_s: float,
    pole_pairs: int,
) -> DecodedSamples:
    """Ramp every leg (from_rpm, to_rpm) in turn and return their samples as one record (the legs follow each
    other in the stream without a break); the load's full ramp is put back after the last."""
    ramps = [ramp_speed(session, commands, a, b, rate_rpm_per_s, pole_pairs) for a, b in legs]
    commands.restore_full_ramp()
    return DecodedSamples.concat(ramps)
