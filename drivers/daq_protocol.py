"""DAQ stream frame format (docs/interfaces.md, "DAQ stream frame"): encoding and vectorised decoding.

One little-endian frame of 12 bytes per sample:

    0  2 bytes  sync 0xA5 0x5A
    2  uint16   sequence number, +1 per sample, wraps at 65536
    4  uint16   electrical rotor angle, 65536 = 2*pi
    6  int16    angular acceleration, +-32767 = +- sensor full scale
    8  uint16   status flags (FLAG_*)
   10  uint16   CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) over bytes 2..9

Both ends of the wire read the layout from here: the reader decodes with `FrameDecoder`, which
works on whole byte chunks with numpy (no per-frame Python) so that decoding keeps up with millions
of samples per second; the emulator's numba frame writer (plant_emulator/physics/daq.py) takes the
sync bytes, field offsets, CRC table, CRC step and flag bits below as compile-time constants, and
`encode_frames` is the vectorised encoder for tools and tests.

What the decoder counts (DecoderCounters) keeps line errors apart from the holes the reader makes
or knows of: `crc_failures`, `sequence_gaps`, `samples_lost`, `bytes_skipped` and `resyncs` are line
errors only. The reader tells the decoder when it flushed the port (`note_flush`: the realignment
and sequence jump at the next valid frame are the flush's, counted as `flush_*`), when it paused for
backpressure (`note_pause`: a DAQ that streams on overflows meanwhile, so whole frames missing with
intact bytes around them in what follows are an `overrun`), and when it reopened a lost port
(`note_reconnect`: the jump is the disconnect's, which the reader counts).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

FRAME_BYTES = 12
SYNC = b"\xa5\x5a"
SYNC_0, SYNC_1 = SYNC  # the two sync bytes as ints (0xA5, 0x5A)
FLAG_OVER_RANGE = 1 << 0
FLAG_SENSOR_FAULT = 1 << 1
FLAG_SYNC_INPUT = 1 << 2
FLAGS_DEFINED = FLAG_OVER_RANGE | FLAG_SENSOR_FAULT | FLAG_SYNC_INPUT
ANGLE_COUNTS_PER_TURN = 65536
ACCEL_FULL_SCALE_COUNTS = 32767

FRAME_DTYPE = np.dtype(
    [
        ("sync0", "u1"),
        ("sync1", "u1"),
        ("seq", "<u2"),
        ("angle", "<u2"),
        ("accel", "<i2"),
        ("flags", "<u2"),
        ("crc", "<u2"),
    ]
)
assert FRAME_DTYPE.itemsize == FRAME_BYTES
# byte offsets of the little-endian uint16/int16 fields, from the dtype
_FIELDS: Mapping[str, tuple[Any, ...]] = FRAME_DTYPE.fields or {}  # a structured dtype: never None
OFFSET_SEQ = _FIELDS["seq"][1]
OFFSET_ANGLE = _FIELDS["angle"][1]
OFFSET_ACCEL = _FIELDS["accel"][1]
OFFSET_FLAGS = _FIELDS["flags"][1]
OFFSET_CRC = _FIELDS["crc"][1]
CRC_FIRST, CRC_STOP = OFFSET_SEQ, OFFSET_CRC  # the CRC covers bytes [CRC_FIRST, CRC_STOP)
CRC_INIT = 0xFFFF


def _crc_table() -> np.ndarray:
    table = np.zeros(256, dtype=np.uint16)
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
        table[byte] = crc & 0xFFFF
    return table


CRC_TABLE = _crc_table()


def crc16_step(crc: int, byte: int) -> int:
    """One byte into a CRC-16/CCITT-FALSE register (table-driven). Plain Python that numba also
    compiles: the emulator's frame writer jits this very function."""
    return ((crc << 8) & 0xFFFF) ^ int(CRC_TABLE[((crc >> 8) ^ byte) & 0xFF])


def crc16_ccitt_false(data: bytes) -> int:
    """CRC-16/CCITT-FALSE of one byte string (check value for b'123456789' is 0x29B1)."""
    crc = CRC_INIT
    for byte in data:
        crc = crc16_step(crc, byte)
    return crc


def crc16_rows(rows: np.ndarray) -> np.ndarray:
    """CRC-16/CCITT-FALSE of every row of a (n, k) uint8 array, table-driven one column at a time."""
    crc = np.full(rows.shape[0], CRC_INIT, dtype=np.uint16)
    for col in range(rows.shape[1]):
        crc = (crc << np.uint16(8)) ^ CRC_TABLE[(crc >> np.uint16(8)) ^ rows[:, col]]
    return crc


def encode_frames(seq: np.ndarray, angle_counts: np.ndarray, accel_counts: np.ndarray, flags: np.ndarray) -> bytes:
    """Frames for n samples; inputs are arrays of the wire integers (seq wraps modulo 65536)."""
    n = len(seq)
    frames = np.zeros(n, dtype=FRAME_DTYPE)
    frames["sync0"], frames["sync1"] = SYNC_0, SYNC_1
    frames["seq"] = np.asarray(seq, dtype=np.int64) & 0xFFFF
    frames["angle"] = np.asarray(angle_counts, dtype=np.int64) & 0xFFFF
    frames["accel"] = accel_counts
    frames["flags"] = flags
    raw = frames.view(np.uint8).reshape(n, FRAME_BYTES)
    frames["crc"] = crc16_rows(raw[:, CRC_FIRST:CRC_STOP])
    return frames.tobytes()


@dataclass
class DecodedSamples:
    """Samples decoded from one chunk, in stream order.

    index: unwrapped sample number (the measurement clock; continues across the 65536 wrap).
    gap_before: True where samples were lost or a bad frame was skipped just before this sample.
    """

    index: np.ndarray
    angle_rad: np.ndarray
    accel_fs: np.ndarray
    flags: np.ndarray
    gap_before: np.ndarray

    def __len__(self) -> int:
        return len(self.index)

    FIELDS = ("index", "angle_rad", "accel_fs", "flags", "gap_before")

    def slice(self, start: int, stop: int | None = None) -> "DecodedSamples":
        return DecodedSamples(*(getattr(self, name)[start:stop] for name in self.FIELDS))

    @classmethod
    def concat(cls, blocks: list["DecodedSamples"]) -> "DecodedSamples":
        """Blocks joined in order (one block is returned as is)."""
        if len(blocks) == 1:
            return blocks[0]
        return cls(*(np.concatenate([getattr(b, name) for b in blocks]) for name in cls.FIELDS))

    @classmethod
    def empty(cls) -> "DecodedSamples":
        return cls(np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0, np.uint16), np.zeros(0, bool))


OVERRUN_WINDOW_BYTES = 1 << 18
"""After a backpressure pause, whole frames missing within this many bytes are an overrun: more
than a serial port's OS buffers hold (tty flip buffers and line discipline, USB transfers), so the
hole where the DAQ overflowed lies inside it."""


@dataclass
class DecoderCounters:
    """Cumulative counts. Line errors: crc_failures, sequence_gaps (holes in the sequence with damaged
    or missing bytes, or without a known cause), samples_lost (in those holes), bytes_skipped, resyncs.
    Not line errors: flush_* (what the reader's own flush of the port discarded: the resync and jump
    right after it), overruns (whole frames missing, bytes intact, after a backpressure pause: the
    DAQ overflowed while nobody read) and overrun_samples_lost."""

    frames: int = 0
    crc_failures: int = 0
    sequence_gaps: int = 0
    samples_lost: int = 0
    bytes_skipped: int = 0
    resyncs: int = 0
    flush_resyncs: int = 0
    flush_bytes_skipped: int = 0
    flush_samples_lost: int = 0
    overruns: int = 0
    overrun_samples_lost: int = 0


@dataclass
class FrameDecoder:
    """Stateful decoder: feed byte chunks, get samples. Resynchronises on sync + valid CRC."""

    counters: DecoderCounters = field(default_factory=DecoderCounters)
    _pending: bytes = b""
    _last_seq: int | None = None
    _last_index: int = -1
    _bad_since_last: bool = False
    _break: str | None = None  # "flush" / "reconnect": the next valid frame's hole is this one's
    _overrun_bytes_left: int = 0  # bytes after a backpressure pause in which a clean jump is an overrun

    def note_flush(self) -> None:
        """The port's input buffer was just discarded: the resync and sequence jump before the next
        valid frame are the flush's (flush_* counters), not line errors."""
        self._break = "flush"

    def note_reconnect(self) -> None:
        """The port was reopened after it was lost: the hole before the next valid frame is the
        disconnect's (the reader counts disconnects), not a line error."""
        self._break = "reconnect"

    def note_pause(self) -> None:
        """The reader stopped reading for backpressure: a DAQ streams on and overflows meanwhile, so
        whole frames missing in the next OVERRUN_WINDOW_BYTES are an overrun, not a line error."""
        self._overrun_bytes_left = OVERRUN_WINDOW_BYTES

    def feed(self, chunk: bytes) -> DecodedSamples:
        in_overrun_window = self._overrun_bytes_left > 0
        self._overrun_bytes_left = max(0, self._overrun_bytes_left - len(chunk))
        buf = self._pending + chunk
        arr = np.frombuffer(buf, dtype=np.uint8)
        n = len(arr)
        if n < FRAME_BYTES:
            self._pending = buf
            return DecodedSamples.empty()
        # candidate frame starts: every sync pattern with a whole frame after it
        cand = np.flatnonzero((arr[: n - FRAME_BYTES + 1] == SYNC_0) & (arr[1 : n - FRAME_BYTES + 2] == SYNC_1))
        rows = arr[cand[:, None] + np.arange(FRAME_BYTES)] if len(cand) else np.zeros((0, FRAME_BYTES), np.uint8)
        crc_ok = crc16_rows(rows[:, CRC_FIRST:CRC_STOP]) == (
            rows[:, OFFSET_CRC].astype(np.uint16) | (rows[:, OFFSET_CRC + 1].astype(np.uint16) << 8)
        )
        starts = cand[crc_ok]
        # a valid frame may contain a false sync pattern with a (rare) valid CRC: keep non-overlapping ones
        if len(starts) > 1 and np.any(np.diff(starts) < FRAME_BYTES):
            starts = _non_overlapping(starts)
        bad_candidates = cand[~crc_ok]
        if len(bad_candidates) and len(starts):
            # a sync with a bad CRC inside a good frame is just payload, not a failure
            inside = np.searchsorted(starts, bad_candidates, side="right") - 1
            covered = (inside >= 0) & (bad_candidates < starts[np.maximum(inside, 0)] + FRAME_BYTES)
            bad_candidates = bad_candidates[~covered]
        end = int(starts[-1]) + FRAME_BYTES if len(starts) else 0
        keep_from = max(end, n - FRAME_BYTES + 1)
        self._pending = buf[keep_from:]
        # bytes not covered by a frame (before, between, after frames) were skipped; after a flush or
        # a reconnect, what comes before the first valid frame is that break's, not the line's
        covered_bytes = len(starts) * FRAME_BYTES
        skipped = keep_from - covered_bytes
        broken = self._break
        head = int(starts[0]) if len(starts) else keep_from
        if broken is not None:
            line_skipped = skipped - head
            line_crc_failures = int(np.count_nonzero(bad_candidates >= head))
            if broken == "flush":
                self.counters.flush_bytes_skipped += head
        else:
            line_skipped = skipped
            line_crc_failures = len(bad_candidates)
        self.counters.crc_failures += line_crc_failures
        if line_skipped:
            self.counters.bytes_skipped += line_skipped
            self.counters.resyncs += 1
        if not len(starts):
            self._bad_since_last = self._bad_since_last or skipped > 0
            return DecodedSamples.empty()
        frames = (
            np.frombuffer(buf, dtype=np.uint8)[starts[:, None] + np.arange(FRAME_BYTES)]
            .copy()
            .view(FRAME_DTYPE)
            .ravel()
        )
        seq = frames["seq"].astype(np.int64)
        prev = np.empty_like(seq)
        prev[1:] = seq[:-1]
        prev[0] = seq[0] - 1 if self._last_seq is None else self._last_seq
        step = (seq - prev) % 65536
        step[step == 0] = 1  # a repeated sequence number is treated as a one-sample step and flagged below
        gap = (seq - prev) % 65536 != 1
        # a frame that was skipped between two good frames breaks contiguity even if seq looks fine
        gap_bytes = np.zeros(len(starts), dtype=bool)
        gap_bytes[1:] = np.diff(starts) != FRAME_BYTES
        gap_bytes[0] = (starts[0] != 0 and self._last_seq is not None) or self._bad_since_last
        gap_before = gap | gap_bytes
        if self._last_seq is None:
            gap_before[0] = False
            gap[0] = False
        index = self._last_index + np.cumsum(step)
        if self._last_seq is None:
            index = index - index[0]
        lost = np.where(gap, step - 1, 0)
        line_gap = gap.copy()
        if broken is not None:
            # the first valid frame after a flush / reconnect: its hole is the break's
            if broken == "flush":
                self.counters.flush_samples_lost += int(lost[0])
                self.counters.flush_resyncs += int(bool(gap_before[0]) or head > 0)
            line_gap[0] = False
            self._break = None
        if in_overrun_window:
            # whole frames missing with intact bytes around them: the DAQ dropped them (overflow)
            clean = line_gap & ~gap_bytes
            self.counters.overruns += int(np.count_nonzero(clean))
            self.counters.overrun_samples_lost += int(lost[clean].sum())
            line_gap &= ~clean
        self.counters.sequence_gaps += int(np.count_nonzero(line_gap))
        self.counters.samples_lost += int(lost[line_gap].sum())
        self.counters.frames += len(starts)
        self._last_seq = int(seq[-1])
        self._last_index = int(index[-1])
        self._bad_since_last = False
        return DecodedSamples(
            index=index,
            angle_rad=frames["angle"].astype(np.float64) * (2.0 * math.pi / ANGLE_COUNTS_PER_TURN),
            accel_fs=frames["accel"].astype(np.float64) / ACCEL_FULL_SCALE_COUNTS,
            flags=frames["flags"].copy(),
            gap_before=gap_before,
        )


def _non_overlapping(starts: np.ndarray) -> np.ndarray:
    kept = [int(starts[0])]
    for s in starts[1:]:
        if s >= kept[-1] + FRAME_BYTES:
            kept.append(int(s))
    return np.asarray(kept, dtype=starts.dtype)
