"""The recordings directory, its retention, and each result's record of its recording (the file itself:
service/store/recordings/recorder.py).

`RecordingStore` writes the file once the result row exists (its id names the file and goes into the
header), records in the row whether the recording exists (`results.recording_json`, a result record's `recording`), and applies the
retention (`[recordings] keep_gb`: the newest recordings up to that many GB are kept, older ones are
deleted after each write; the one just written is always kept). No storage error (directory not
writable, disk full, asammdf failing) ever reaches the measurement or loses the result: the row is
stored and says why its recording failed, in words that name no server path (the API shows them; the
service's log has the paths).
"""

from __future__ import annotations

import json
import logging
import os
import re
from pathlib import Path
from typing import Any, BinaryIO, Mapping

from service import __version__
from service.errors import NotFound
from service.store.recordings.recorder import RecordingWriteError, RunRecorder, pathless_reason
from service.store.storage import Storage, now_iso

log = logging.getLogger(__name__)

BYTES_PER_GB = 1e9
_FILE_NAME = re.compile(r"^result-(\d+)\.mf4$")


def recordings_directory(directory: str | None, database_files: Path) -> Path:
    """The configured directory, or `recordings` in the database's files directory (beside a SQLite file;
    the user's data directory for a server, Storage.files_directory); made absolute once, at start (as
    the database path: a relative one is taken against the working directory)."""
    path = Path(directory).expanduser() if directory else Path(database_files).expanduser() / "recordings"
    return path.absolute()


class RecordingUnavailable(NotFound):
    """A result has no raw recording to hand out; the message says why (and names no server path)."""


class RecordingStore:
    """The recordings directory, its retention, and each result's record of its recording."""

    def __init__(
        self,
        storage: Storage,
        directory: Path,
        keep_gb: float,
        sample_rate_hz: float,
        accel_full_scale_rad_s2: float,
        enabled: bool = True,
    ):
        self.storage = storage
        self.directory = directory
        self.keep_gb = keep_gb
        self.sample_rate_hz = sample_rate_hz
        self.accel_full_scale_rad_s2 = accel_full_scale_rad_s2
        self.enabled = enabled

    def recorder(self) -> RunRecorder | None:
        """A recorder for one identification (None: recordings are switched off)."""
        if not self.enabled:
            return None
        return RunRecorder(self.directory, self.sample_rate_hz, self.accel_full_scale_rad_s2)

    def path(self, result_id: int) -> Path:
        return self.directory / f"result-{result_id}.mf4"

    def keep(self, recorder: RunRecorder | None, result_id: int, row: dict[str, Any]) -> None:
        """Write the recording of stored result `result_id` (its row as stored), note in the row
        whether it exists, then apply the retention. Never raises: the result is already stored."""
        if recorder is None:
            return
        record: dict[str, Any] = {"format": "mf4", **self._counts(recorder)}
        try:
            if recorder.error is None and not recorder.samples_recorded:
                recorder.close()
                record["error"] = "no DAQ samples: the run ended before the identification read any"
            else:
                path = self.path(result_id)
                record["bytes"] = recorder.write(
                    path,
                    self._header(recorder, result_id, row),
                    f"ripplecal raw recording of result {result_id}: {row['method']} at "
                    f"{row['torque_nm']:g} Nm, {row['speed_rpm']:g} rpm, {row['udc_v']:g} V",
                )
                record["path"] = str(path)
                record["written_at"] = now_iso()
        except Exception as exc:  # noqa: BLE001 - the recording failed, the result stands
            recorder.close()
            record["error"] = recorder.error or (
                str(exc) if isinstance(exc, RecordingWriteError) else f"writing its file failed: {pathless_reason(exc)}"
            )
            log.warning("result %s: raw recording %s failed: %s", result_id, self.path(result_id), record["error"])
        try:
            self.storage.set_result_recording(result_id, record)
        except Exception:  # noqa: BLE001
            log.exception("result %s: could not store its recording's record", result_id)
        if "path" in record:
            self.apply_retention(keep=Path(record["path"]))

    def _counts(self, recorder: RunRecorder) -> dict[str, Any]:
        """What the recording holds, in the result's record and in the file's header alike."""
        return {
            "samples": recorder.samples_recorded,
            "stale_samples": recorder.stale_samples,
            "setpoints": len(recorder.setpoints),
            "sample_rate_hz": self.sample_rate_hz,
        }

    def _header(self, recorder: RunRecorder, result_id: int, row: dict[str, Any]) -> dict[str, Any]:
        return {
            "result_id": result_id,
            "status": row.get("status"),
            "method": row["method"],
            "options": json.dumps(row["options"]) if row.get("options") is not None else None,
            "torque_nm": row["torque_nm"],
            "speed_rpm": row["speed_rpm"],
            "udc_v": row["udc_v"],
            "harmonic_order": row.get("harmonic_order"),
            "plant_time_s": row.get("plant_time_s"),
            **self._counts(recorder),
            "accel_full_scale_rad_s2": self.accel_full_scale_rad_s2,
            "bench_identity": row.get("bench_identity"),
            "software_version": row.get("software_version", __version__),
            "started_at": row.get("started_at"),
            "finished_at": row.get("finished_at"),
            "sweep_id": row.get("sweep_id"),
            "job_id": row.get("job_id"),
        }

    def apply_retention(self, keep: Path | None = None) -> list[int]:
        """Delete the oldest recordings until the rest fit in keep_gb (`keep` is never deleted); the
        results whose recordings went say so. Returns their ids."""
        files = []
        for entry in os.scandir(self.directory):
            m = _FILE_NAME.match(entry.name)
            if m and entry.is_file():
                st = entry.stat()
                files.append((st.st_mtime_ns, int(m.group(1)), Path(entry.path), st.st_size))
        files.sort()  # oldest first (ties: lower result id first)
        total = sum(f[3] for f in files)
        limit = self.keep_gb * BYTES_PER_GB
        deleted: list[int] = []
        for _, result_id, path, size in files:
            if total <= limit:
                break
            if keep is not None and path == keep:
                continue
            try:
                path.unlink()
            except FileNotFoundError:
                pass
            except OSError as exc:
                log.warning("retention could not delete %s: %s", path, exc)
                continue
            total -= size
            deleted.append(result_id)
        if deleted:
            reason = (
                f"deleted by retention at {now_iso()}: the newest recordings are kept up to "
                f"recordings.keep_gb = {self.keep_gb:g} GB"
            )
            try:
                self.storage.mark_recordings_deleted(deleted, reason)
            except Exception:  # noqa: BLE001
                log.exception("could not mark recordings %s as deleted", deleted)
        return deleted

    def open(self, result_id: int) -> BinaryIO:
        """The recording of a stored result, open for reading (retention may delete it while it is sent:
        an open file stays readable), or RecordingUnavailable saying why there is none."""
        row = self.storage.get_result(result_id)
        if row is None:
            raise RecordingUnavailable(f"result {result_id} does not exist")
        record = recording_record(row)
        if record is None:
            raise RecordingUnavailable(
                f"result {result_id} has no raw recording (it was measured while recordings "
                "were switched off, or before they were kept)"
            )
        why = unavailable_reason(record)
        if why is not None:
            raise RecordingUnavailable(f"result {result_id} has no raw recording: {why}")
        path = Path(record["path"])
        try:
            return path.open("rb")
        except FileNotFoundError:
            log.warning("result %s: its raw recording %s is missing", result_id, path)
            raise RecordingUnavailable(
                f"the raw recording of result {result_id} is missing: its file was deleted "
                "or moved outside ripplecal (the service's log names it)"
            ) from None
        except OSError as exc:
            log.warning("result %s: its raw recording %s cannot be read: %s", result_id, path, exc)
            raise RecordingUnavailable(
                f"the raw recording of result {result_id} cannot be read "
                f"({pathless_reason(exc)}; the service's log names the file)"
            ) from None


def recording_record(row: Mapping[str, Any]) -> dict[str, Any] | None:
    """What a result row says about its recording (None: none was attempted)."""
    return row.get("recording") or None


def unavailable_reason(record: dict[str, Any]) -> str | None:
    """Why a recording that was attempted cannot be had (None: it was written and is kept)."""
    return record.get("deleted") or record.get("error") or (None if record.get("path") else "not written")
