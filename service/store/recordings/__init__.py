"""Raw recordings: the DAQ samples and theta setpoints of every identification, as ASAM MDF 4 files.

Two parts: the file of one identification (recorder.py: `RunRecorder` writes it, `header_properties`
reads its header back) and where the files are kept (store.py: `RecordingStore`, the directory, its
retention, each result's record of its recording). The names the layers above use are imported from here."""

from __future__ import annotations

from service.store.recordings.recorder import (
    DAQ_CHANNELS,
    RECORDING_FORMATS,
    SETPOINT_CHANNELS,
    RunRecorder,
    header_properties,
)
from service.store.recordings.store import (
    RecordingStore,
    RecordingUnavailable,
    recording_record,
    recordings_directory,
    unavailable_reason,
)

__all__ = [
    "DAQ_CHANNELS",
    "RECORDING_FORMATS",
    "SETPOINT_CHANNELS",
    "RecordingStore",
    "RecordingUnavailable",
    "RunRecorder",
    "header_properties",
    "recording_record",
    "recordings_directory",
    "unavailable_reason",
]
