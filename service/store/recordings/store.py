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
from typing import Any, BinaryIO, Callable, Mapping

from service import __version__
from service.errors import NotFound
from service.store.recordings.recorder import RecordingWriteError, RunRecorder, pathless_reason
from service.store.storage import Storage, now_iso

log = logging.getLogger(__name__)

BYTES_PER_GB = 1e9
_FILE_NAME = re.compile(r"^(result|runup)-(\d+)\.mf4$")
_TABLE_OF = {"result": "results", "runup": "runups"}  # a file's prefix -> the table whose row records it


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

    def path(self, result_id: int, prefix: str = "result") -> Path:
        """The file of a result's recording (prefix `runup`: a run-up's, by its row's id)."""
        return self.directory / f"{prefix}-{result_id}.mf4"

    def keep(self, recorder: RunRecorder | None, result_id: int, row: dict[str, Any]) -> None:
        """Write the recording of stored result `result_id` (its row as stored), note in the row
        whether it exists, then apply the retention. Never raises: the result is already stored."""
        description = (
            f"ripplecal raw recording of result {result_id}: {row['method']} at "
            f"{row['torque_nm']:g} Nm, {row['speed_rpm']:g} rpm, {row['udc_v']:g} V"
        )
        self._keep(
            recorder,
            self.path(result_id),
            lambda: self._header(recorder, result_id, row) if recorder is not None else {},
            description,
            lambda record: self.storage.set_result_recording(result_id, record),
            f"result {result_id}",
        )

    def keep_runup(self, recorder: RunRecorder | None, runup_id: int, row: dict[str, Any]) -> None:
        """As keep, for stored run-up `runup_id` (its row: request, result)."""
        req = row["request"]
        lo, hi = req["speed_rpm"]
        description = (
            f"ripplecal raw recording of run-up {runup_id}: {lo:g} -> {hi:g} rpm ({req['direction']}) at "
            f"{req['rate_rpm_per_s']:g} rpm/s, {req['torque_nm']:g} Nm, {req['udc_v']:g} V, injection {req['injection']}"
        )

        def header() -> dict[str, Any]:
            assert recorder is not None
            return {
                "runup_id": runup_id,
                "job_id": row.get("job_id"),
                "request": json.dumps(req),
                **self._counts(recorder),
                "accel_full_scale_rad_s2": self.accel_full_scale_rad_s2,
                "bench_identity": row.get("bench_identity"),
                "software_version": row.get("software_version", __version__),
                "started_at": row.get("started_at"),
                "finished_at": row.get("finished_at"),
            }

        self._keep(
            recorder,
            self.path(runup_id, "runup"),
            header,
            description,
            lambda record: self.storage.set_runup_recording(runup_id, record),
            f"run-up {runup_id}",
        )

    def _keep(
        self,
        recorder: RunRecorder | None,
        path: Path,
        header: Callable[[], dict[str, Any]],
        description: str,
        set_record: Callable[[dict[str, Any]], None],
        what: str,
    ) -> None:
        if recorder is None:
            return
        record: dict[str, Any] = {"format": "mf4", **self._counts(recorder)}
        try:
            if recorder.error is None and not recorder.samples_recorded:
                recorder.close()
                record["error"] = "no DAQ samples: the run ended before the measurement read any"
            else:
                record["bytes"] = recorder.write(path, header(), description)
                record["path"] = str(path)
                record["written_at"] = now_iso()
        except Exception as exc:  # noqa: BLE001 - the recording failed, the result stands
            recorder.close()
            record["error"] = recorder.error or (
                str(exc) if isinstance(exc, RecordingWriteError) else f"writing its file failed: {pathless_reason(exc)}"
            )
            log.warning("%s: raw recording %s failed: %s", what, path, record["error"])
        try:
            set_record(record)
        except Exception:  # noqa: BLE001
            log.exception("%s: could not store its recording's record", what)
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
                files.append((st.st_mtime_ns, m.group(1), int(m.group(2)), Path(entry.path), st.st_size))
        files.sort()  # oldest first (ties: results first, lower id first)
        total = sum(f[4] for f in files)
        limit = self.keep_gb * BYTES_PER_GB
        deleted: dict[str, list[int]] = {}
        for _, prefix, row_id, path, size in files:
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
            deleted.setdefault(prefix, []).append(row_id)
        reason = (
            f"deleted by retention at {now_iso()}: the newest recordings are kept up to "
            f"recordings.keep_gb = {self.keep_gb:g} GB"
        )
        for prefix, row_ids in deleted.items():
            try:
                self.storage.mark_recordings_deleted(row_ids, reason, _TABLE_OF[prefix])
            except Exception:  # noqa: BLE001
                log.exception("could not mark %s recordings %s as deleted", prefix, row_ids)
        return deleted.get("result", [])

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
