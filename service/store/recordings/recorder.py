"""The raw recording of one identification: the DAQ samples and theta setpoints it read, as an ASAM MDF 4
file (the writer, `RunRecorder`; the reader of its header, `header_properties`).

A `RunRecorder` is handed to one identification (engine -> identify_at -> the measurement session).
The session gives it every sample it consumes from the DAQ stream between the method's first and
last read, in stream order, each marked counted (part of the result's plant_time_s: the settling
after each setpoint and every window, discarded ones included) or stale (read while waiting for a
setpoint to take effect), and each theta setpoint with the DAQ sample at which it took effect (its
sync-line toggle, service/bench/measurement.py). The file holds the counted samples; stale ones are only
counted (`stale_samples` in the header): on a real bench they are the few samples of CAN latency,
in the emulator's fast mode the 1-2 s per setpoint that the DAQ path had buffered, which would make
a recording 60 times its plant time. So, per recording:

    samples = plant_time_s * sample_rate_hz   (exactly, when the DAQ lost no sample: plant time is
                                               counted over sample indices, see `gap_before`)

and a setpoint's `effect_sample_index` is the first sample of its segment (sample_index jumps there
by the stale samples left out).

Memory stays bounded: samples are kept as their wire integers (15 bytes each) and spilled every
CHUNK_SAMPLES to the recorder's spool, a temporary file in the recordings directory that has no name
(it counts on the same disk, and nothing of it is left behind whatever becomes of the recorder: a failed
result insert, a crash, a kill); only the setpoints (tens to a few thousand per identification) stay in
memory until the file is written: at most CHUNK_SAMPLES x 15 B (1 MB) plus the session's largest single
read (one window) is held. asammdf (and its own temporary file) is used only while the file is written,
a chunk at a time, and closed however the write ends.
"""

from __future__ import annotations

import logging
import math
import os
import re
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, BinaryIO, Iterator

import numpy as np
from asammdf import MDF, Signal

from drivers.daq_protocol import (
    ACCEL_FULL_SCALE_COUNTS,
    ANGLE_COUNTS_PER_TURN,
    FLAG_OVER_RANGE,
    FLAG_SENSOR_FAULT,
    FLAG_SYNC_INPUT,
    DecodedSamples,
)
from service.model.secondary_path import gamma_delta

log = logging.getLogger(__name__)

RECORDING_FORMATS = {"mf4": "ASAM MDF 4.10 (asammdf, CANape, the asammdf GUI)"}
CHUNK_SAMPLES = 65536  # samples handed to asammdf at once (4 s at 16 kHz, about 1 MB)

# channel names, read back by tests and tools
DAQ_GROUP, SETPOINT_GROUP = "daq", "theta_setpoints"
DAQ_CHANNELS = ("sample_index", "angle", "alpha", "flags", "gap_before")
SETPOINT_CHANNELS = ("effect_sample_index", "theta_cos", "theta_sin", "gamma", "delta")
# one sample in the spool: the wire integers, packed (15 bytes)
_WIRE = np.dtype([("index", "<i8"), ("angle", "<u2"), ("alpha", "<i2"), ("flags", "<u2"), ("gap", "u1")])


class RecordingWriteError(RuntimeError):
    """A recording could not be written; the message says why and names no server path."""


def pathless_reason(exc: BaseException) -> str:
    """An exception in words that name no path (an OSError's text carries its file name)."""
    if isinstance(exc, OSError) and exc.strerror:
        return f"{type(exc).__name__}: {exc.strerror}"
    return f"{type(exc).__name__}: {exc}"


@dataclass
class _Setpoint:
    effect_index: int
    theta_cos_rad: float
    theta_sin_rad: float


class RunRecorder:
    """What one identification read from the DAQ, and its theta setpoints. Never raises into the
    measurement: a failure is kept in `error` and recording stops there."""

    def __init__(
        self, directory: Path, sample_rate_hz: float, accel_full_scale_rad_s2: float, chunk_samples: int = CHUNK_SAMPLES
    ):
        self.directory = directory
        self.sample_rate_hz = sample_rate_hz
        self.accel_full_scale_rad_s2 = accel_full_scale_rad_s2
        self.chunk_samples = chunk_samples
        self.error: str | None = None
        self.samples_recorded = 0
        self.stale_samples = 0  # read before a setpoint took effect: counted, not kept
        self.started_at: datetime | None = None
        self.setpoints: list[_Setpoint] = []
        self._parts: list[np.ndarray] = []
        self._buffered = 0
        self._spool: BinaryIO | None = None
        try:
            if directory.exists() and not directory.is_dir():
                raise NotADirectoryError(20, "a file stands where it should be", str(directory))
            directory.mkdir(parents=True, exist_ok=True)
            # no name in the directory (O_TMPFILE, or unlinked at once): gone with the recorder, whatever happens
            self._spool = tempfile.TemporaryFile(dir=directory)
        except Exception as exc:  # noqa: BLE001 - any storage problem is the recording's, not the run's
            self._fail(
                "the recordings directory is unusable (check recordings.directory)",
                exc,
                f"recordings directory {directory} unusable",
            )

    # --- fed by the measurement session -----------------------------------------------------------
    def samples(self, s: DecodedSamples, counted: bool) -> None:
        """Samples the session consumed, in stream order; `counted`: part of the plant time (kept),
        else read before a setpoint took effect (counted only)."""
        if not counted:
            self.stale_samples += len(s)
            return
        if self.error is not None or not len(s):
            return
        if self.started_at is None:
            self.started_at = datetime.now(timezone.utc)
        n = len(s)
        # back to the wire integers (exact: the decoder scaled them by these constants)
        part = np.empty(n, _WIRE)
        part["index"] = s.index
        part["angle"] = (
            np.rint(s.angle_rad * (ANGLE_COUNTS_PER_TURN / (2.0 * math.pi))).astype(np.int64).astype(np.uint16)
        )
        part["alpha"] = np.rint(s.accel_fs * ACCEL_FULL_SCALE_COUNTS).astype(np.int16)
        part["flags"] = s.flags
        part["gap"] = s.gap_before
        self._parts.append(part)
        self._buffered += n
        self.samples_recorded += n
        if self._buffered >= self.chunk_samples:
            self._spill()

    def setpoint(self, effect_index: int, theta_cos_rad: float, theta_sin_rad: float) -> None:
        """A theta setpoint and the DAQ sample at which it took effect."""
        if self.error is None:
            self.setpoints.append(_Setpoint(int(effect_index), float(theta_cos_rad), float(theta_sin_rad)))

    # --- to the file ----------------------------------------------------------------------------------
    def _spill(self) -> None:
        """The samples held in memory to the spool."""
        if not self._parts or self.error is not None:
            return
        block = np.concatenate(self._parts)
        self._parts, self._buffered = [], 0
        try:
            assert self._spool is not None  # opened with the recorder unless `error` says why not
            self._spool.write(block.tobytes())
        except Exception as exc:  # noqa: BLE001 - disk full: the run goes on without its recording
            self._fail("spooling the DAQ samples failed", exc)

    def _spooled_chunks(self) -> Iterator[tuple[np.ndarray, ...]]:
        """The spooled samples back, CHUNK_SAMPLES at a time: (t, index, angle, alpha, flags, gap)."""
        assert self._spool is not None  # write() read `error` first
        self._spool.seek(0)
        while data := self._spool.read(self.chunk_samples * _WIRE.itemsize):
            block = np.frombuffer(data, _WIRE)
            index = block["index"].copy()
            yield (index / self.sample_rate_hz, index, *(block[k].copy() for k in ("angle", "alpha", "flags", "gap")))

    def _daq_signals(
        self,
        t: np.ndarray,
        index: np.ndarray,
        angle: np.ndarray,
        alpha: np.ndarray,
        flags: np.ndarray,
        gap: np.ndarray,
    ) -> list[Signal]:
        return [
            Signal(
                index,
                t,
                name="sample_index",
                unit="sample",
                comment="DAQ sample counter (unwrapped); the measurement clock",
            ),
            Signal(
                angle,
                t,
                name="angle",
                unit="rad",
                conversion={"a": 2.0 * math.pi / ANGLE_COUNTS_PER_TURN, "b": 0.0},
                comment="electrical rotor angle phi_e (encoder), 65536 counts per turn",
            ),
            Signal(
                alpha,
                t,
                name="alpha",
                unit="rad/s^2",
                conversion={"a": self.accel_full_scale_rad_s2 / ACCEL_FULL_SCALE_COUNTS, "b": 0.0},
                comment=f"angular acceleration, +-{ACCEL_FULL_SCALE_COUNTS} counts = +-sensor full scale "
                f"({self.accel_full_scale_rad_s2:g} rad/s^2, daq.accel_full_scale_rad_s2)",
            ),
            Signal(
                flags,
                t,
                name="flags",
                unit="",
                comment=f"DAQ status bits (values): {FLAG_OVER_RANGE} over range, {FLAG_SENSOR_FAULT} sensor fault, "
                f"{FLAG_SYNC_INPUT} drive sync line (toggles once per applied setpoint)",
            ),
            Signal(
                gap,
                t,
                name="gap_before",
                unit="",
                comment="1: samples were lost or a bad frame skipped just before this sample",
            ),
        ]

    def _setpoint_signals(self) -> list[Signal]:
        effect = np.array([p.effect_index for p in self.setpoints], np.int64)
        t = effect / self.sample_rate_hz
        tc = np.array([p.theta_cos_rad for p in self.setpoints])
        ts = np.array([p.theta_sin_rad for p in self.setpoints])
        gd = np.array([gamma_delta(c, s) for c, s in zip(tc, ts)]).reshape(-1, 2)
        return [
            Signal(
                effect,
                t,
                name="effect_sample_index",
                unit="sample",
                comment="DAQ sample at which the setpoint took effect (its sync-line toggle)",
            ),
            Signal(tc, t, name="theta_cos", unit="rad", comment="theta_cos = gamma cos(delta) (eq. 21-22)"),
            Signal(ts, t, name="theta_sin", unit="rad", comment="theta_sin = -gamma sin(delta) (eq. 21-22)"),
            Signal(np.degrees(gd[:, 0]), t, name="gamma", unit="deg", comment="|theta| (eq. 21)"),
            Signal(np.degrees(gd[:, 1]), t, name="delta", unit="deg", comment="phase of theta, 0..360 (eq. 22)"),
        ]

    def write(self, path: Path, header: dict[str, Any], description: str) -> int:
        """The MF4 file at `path` (written beside it, then renamed: never half a file under its name);
        returns its size in bytes. Raises on a storage error (its message names no path). However it
        ends, nothing is left in the directory but the file, and the recorder is closed."""
        mdf = None
        partial = path.with_name(path.stem + ".partial.mf4")  # asammdf insists on the .mf4 suffix
        try:
            self._spill()
            if self.error is not None:
                raise RecordingWriteError(self.error)
            # asammdf keeps appended data in a temporary file: in the recordings directory (the same disk)
            mdf = MDF(version="4.10", temporary_folder=str(self.directory))
            for i, (t, index, angle, alpha, flags, gap) in enumerate(self._spooled_chunks()):
                if i == 0:
                    mdf.append(
                        self._daq_signals(t, index, angle, alpha, flags, gap),
                        acq_name=DAQ_GROUP,
                        comment="DAQ samples the identification counted as plant time, in stream order; "
                        "time = sample_index / sample rate",
                    )
                else:
                    mdf.extend(0, [(t, None), *((x, None) for x in (index, angle, alpha, flags, gap))])
            if self.setpoints:
                mdf.append(
                    self._setpoint_signals(),
                    acq_name=SETPOINT_GROUP,
                    comment="theta setpoints; time = effect_sample_index / sample rate",
                )
            mdf.header.start_time = self.started_at or datetime.now(timezone.utc)
            mdf.header.comment = _header_xml(description, header)
            mdf.save(partial, overwrite=True, compression=2)  # 2: transposed deflate (MDF 4.10 DZ blocks)
            os.replace(partial, path)
        except RecordingWriteError:
            raise
        except Exception as exc:
            log.warning("writing the raw recording %s failed", path, exc_info=True)
            raise RecordingWriteError(f"writing its file failed: {pathless_reason(exc)}") from exc
        finally:
            if mdf is not None:
                _close_mdf(mdf)
                _remove(partial)
            self.close()
        return path.stat().st_size

    def close(self) -> None:
        """Drop what is held (the spool too). Idempotent."""
        self._parts, self._buffered = [], 0
        spool, self._spool = self._spool, None
        if spool is not None:
            try:
                spool.close()
            except OSError:
                log.debug("closing the recording's spool failed", exc_info=True)

    def _fail(self, what: str, exc: BaseException, logged: str | None = None) -> None:
        """Recording stops: `what` (no server path: the API shows it) goes into `error`, `logged` (with
        the path) into the log."""
        self.error = f"{what}: {pathless_reason(exc)}"
        log.warning("raw recording stopped: %s: %s: %s", logged or what, type(exc).__name__, exc)
        self.close()


def _close_mdf(mdf: MDF) -> None:
    """asammdf's MDF closed (its temporary file deleted), whatever state a failed write left it in."""
    if mdf is None:
        return
    try:
        mdf.close()
    except Exception:  # noqa: BLE001 - its temporary file may already be gone
        log.debug("closing asammdf's MDF failed", exc_info=True)


def _remove(path: Path) -> None:
    try:
        path.unlink(missing_ok=True)
    except OSError as exc:
        log.warning("could not remove %s: %s", path, exc)


def _header_xml(description: str, properties: dict[str, Any]) -> str:
    """MDF 4 HDcomment: a description and named properties (shown by CANape and the asammdf GUI)."""
    root = ET.Element("HDcomment")
    ET.SubElement(root, "TX").text = description
    common = ET.SubElement(root, "common_properties")
    for name, value in properties.items():
        ET.SubElement(common, "e", name=name).text = "" if value is None else str(value)
    return ET.tostring(root, encoding="unicode")


def header_properties(comment: str) -> dict[str, str]:
    """The named properties of an HDcomment (the inverse of what `RecordingStore.keep` writes)."""
    root = ET.fromstring(re.sub(r""" xmlns=["'][^"']*["']""", "", comment))
    return {e.attrib["name"]: e.text or "" for e in root.iter("e")}
