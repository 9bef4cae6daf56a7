"""Raw recordings without a bench: the MF4 a recorder writes holds exactly the wire values it was
given (read back with asammdf), memory stays within a chunk, and retention keeps the newest files
up to keep_gb and says so in the results whose recordings it deleted. Whatever fails (the result's
insert, the write), no stray file is left in the recordings directory, and no error names a server path."""

import contextlib
import os
import sqlite3

import numpy as np
import pytest
from asammdf import MDF

from drivers.daq_protocol import ACCEL_FULL_SCALE_COUNTS, FrameDecoder, encode_frames
from service.api.public.results import result_public
from service.model.operating_point import OperatingPoint
from service.settings import SettingsError, load_settings
from service.store.recordings import RecordingStore, RecordingUnavailable, RunRecorder, header_properties
from service.store.result_rows import result_row
from service.store.storage import Storage, StorageUnavailable, now_iso

RATE_HZ, FULL_SCALE = 16_000.0, 500.0


def _decoded(n: int, start: int = 0):
    """n samples through the real wire format (encode, decode)."""
    rng = np.random.default_rng(7)
    seq = np.arange(start, start + n)
    angle = (seq * 97) % 65536
    accel = rng.integers(-ACCEL_FULL_SCALE_COUNTS, ACCEL_FULL_SCALE_COUNTS + 1, n)
    flags = np.where((seq // 500) % 2 == 1, 4, 0)
    return FrameDecoder().feed(encode_frames(seq, angle, accel, flags)), angle, accel, flags


def test_recorder_keeps_the_counted_wire_values_in_chunks(tmp_path):
    recorder = RunRecorder(tmp_path, RATE_HZ, FULL_SCALE, chunk_samples=1000)
    samples, angle, accel, flags = _decoded(3000)
    recorder.samples(samples.slice(0, 200), counted=False)  # read before the setpoint took effect
    recorder.setpoint(200, 0.0, 0.0)
    most_held = 0
    for start in range(200, 3000, 300):
        recorder.samples(samples.slice(start, start + 300), counted=True)
        most_held = max(most_held, recorder._buffered)
        if start == 1400:
            recorder.setpoint(1500, 0.01, -0.02)
    assert most_held < 1000, "the recorder held more than one chunk"
    assert (recorder.samples_recorded, recorder.stale_samples) == (2800, 200)
    path = tmp_path / "result-1.mf4"
    size = recorder.write(path, {"result_id": 1, "method": "probe"}, "test")
    assert size == path.stat().st_size > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result-1.mf4"]  # no temporary file left
    with MDF(path) as mdf:
        np.testing.assert_array_equal(mdf.get("sample_index").samples, np.arange(200, 3000))
        np.testing.assert_allclose(
            mdf.get("alpha").samples, accel[200:] / ACCEL_FULL_SCALE_COUNTS * FULL_SCALE, rtol=0, atol=1e-12
        )
        np.testing.assert_allclose(mdf.get("angle").samples, angle[200:] * 2 * np.pi / 65536, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(mdf.get("flags").samples, flags[200:])
        np.testing.assert_allclose(mdf.get("alpha").timestamps, np.arange(200, 3000) / RATE_HZ, rtol=0, atol=1e-12)
        sp = mdf.get("theta_sin")
        np.testing.assert_array_equal(sp.samples, [0.0, -0.02])
        np.testing.assert_allclose(sp.timestamps, [200 / RATE_HZ, 1500 / RATE_HZ])
        # theta_sin = -gamma sin(delta) (eq. 22): delta of (0.01, -0.02) is atan2(0.02, 0.01)
        np.testing.assert_allclose(mdf.get("delta").samples[1], np.degrees(np.arctan2(0.02, 0.01)))
        assert header_properties(mdf.header.comment) == {"result_id": "1", "method": "probe"}


def test_a_recorder_that_cannot_write_never_raises_into_the_run(tmp_path):
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("")
    recorder = RunRecorder(blocker, RATE_HZ, FULL_SCALE)
    samples, *_ = _decoded(100)
    recorder.samples(samples, counted=True)  # silently ignored
    recorder.setpoint(0, 0.0, 0.0)
    assert "unusable" in recorder.error and str(tmp_path) not in recorder.error  # the API shows it
    with pytest.raises(RuntimeError, match="unusable"):
        recorder.write(blocker / "x.mf4", {}, "")


def _stored_results(storage: Storage, n: int) -> list[int]:
    op = OperatingPoint(torque_nm=1.0, speed_rpm=1000.0, udc_v=12.0)
    return [storage.insert_result(result_row(op, "probe", None, "test-bench", now_iso(), error="x")) for _ in range(n)]


def test_retention_keeps_the_newest_up_to_keep_gb(storage, tmp_path):  # on SQLite and PostgreSQL (tests/conftest.py)
    directory = tmp_path / "recordings"
    directory.mkdir()
    store = RecordingStore(
        storage,
        directory,
        keep_gb=1000e-9,
        sample_rate_hz=RATE_HZ,  # 1000 bytes
        accel_full_scale_rad_s2=FULL_SCALE,
    )
    ids = _stored_results(storage, 5)
    for age, rid in enumerate(reversed(ids)):  # the first result's file is the oldest
        path = store.path(rid)
        path.write_bytes(b"x" * 400)
        os.utime(path, ns=(1_000_000_000_000 - age * 10**9,) * 2)
        storage.set_result_recording(rid, {"format": "mf4", "path": str(path), "bytes": 400})
    (directory / "tmpabc123").write_bytes(b"y" * 5000)  # asammdf's temporary file: not a recording
    deleted = store.apply_retention(keep=store.path(ids[-1]))
    assert deleted == ids[:3]
    assert sorted(p.name for p in directory.iterdir()) == sorted(
        [f"result-{ids[3]}.mf4", f"result-{ids[4]}.mf4", "tmpabc123"]
    )
    for rid in ids[:3]:
        rec = result_public(storage.get_result(rid)).recording
        assert not rec.available and "recordings.keep_gb = 1e-06 GB" in rec.error
        with pytest.raises(RecordingUnavailable, match="deleted by retention"):
            store.open(rid)
    assert result_public(storage.get_result(ids[3])).recording.available
    with store.open(ids[4]) as handle:
        assert handle.read() == b"x" * 400


def test_the_newest_recording_is_kept_even_alone_over_the_limit(
    storage, tmp_path
):  # on SQLite and PostgreSQL (tests/conftest.py)
    store = RecordingStore(storage, tmp_path, keep_gb=1e-9, sample_rate_hz=RATE_HZ, accel_full_scale_rad_s2=FULL_SCALE)
    [rid] = _stored_results(storage, 1)
    store.path(rid).write_bytes(b"x" * 100)
    assert store.apply_retention(keep=store.path(rid)) == []
    assert store.path(rid).exists()


@pytest.mark.parametrize("value", [0, -1.0, float("nan"), float("inf"), "lots"])
def test_keep_gb_must_be_a_positive_finite_number(value):
    with pytest.raises(SettingsError, match="recordings.keep_gb"):
        load_settings(environ={}, overrides={"recordings.keep_gb": value})


@contextlib.contextmanager
def _locked(storage: Storage):
    """Another process holding the database's lock: the storage's inserts fail for real (after 0.1 s)."""
    storage.busy_timeout_s = 0.1
    holder = sqlite3.connect(storage.path, isolation_level=None)
    try:
        holder.execute("PRAGMA locking_mode = EXCLUSIVE")
        holder.execute("BEGIN EXCLUSIVE")
        holder.execute("DELETE FROM api_tokens WHERE id < 0")
        yield
    finally:
        holder.execute("ROLLBACK")
        holder.close()


def test_a_failed_result_insert_leaves_nothing_in_the_recordings_directory(tmp_path):
    """The engine stores the result, then keeps its recording: when the insert fails, the recorder is
    dropped unwritten and unclosed. Its samples never had a name in the directory."""
    storage = Storage(tmp_path / "r.db")
    directory = tmp_path / "recordings"
    store = RecordingStore(storage, directory, keep_gb=1.0, sample_rate_hz=RATE_HZ, accel_full_scale_rad_s2=FULL_SCALE)
    recorder = RunRecorder(directory, RATE_HZ, FULL_SCALE, chunk_samples=1000)  # as store.recorder(), small chunks
    samples, *_ = _decoded(5000)
    recorder.samples(samples, counted=True)  # five chunks spooled
    recorder.setpoint(0, 0.01, 0.0)
    assert recorder.error is None and recorder.samples_recorded == 5000
    assert list(directory.iterdir()) == []  # while it records, too
    row = result_row(
        OperatingPoint(torque_nm=1.0, speed_rpm=1000.0, udc_v=12.0), "probe", None, "test-bench", now_iso(), error="x"
    )
    with _locked(storage), pytest.raises(StorageUnavailable, match="lock"):
        store.keep(recorder, storage.insert_result(row), row)  # never reaches keep
    assert list(directory.iterdir()) == []  # the recorder still alive, unclosed: nothing stray
    recorder.close()
    assert list(directory.iterdir()) == []


def test_a_failed_write_leaves_the_error_in_the_result_and_nothing_in_the_directory(
    storage, tmp_path
):  # on SQLite and PostgreSQL (tests/conftest.py)
    directory = tmp_path / "recordings"
    store = RecordingStore(storage, directory, keep_gb=1.0, sample_rate_hz=RATE_HZ, accel_full_scale_rad_s2=FULL_SCALE)
    recorder = store.recorder()
    samples, *_ = _decoded(3000)
    recorder.samples(samples, counted=True)
    [rid] = _stored_results(storage, 1)
    # the directory goes away between the run and the write: a file stands where it was
    aside = directory.rename(tmp_path / "recordings-aside")
    directory.write_text("not a directory")
    store.keep(recorder, rid, storage.get_result(rid))
    rec = result_public(storage.get_result(rid)).recording
    assert not rec.available and rec.error.startswith("writing its file failed: "), rec
    assert str(tmp_path) not in rec.error
    assert list(aside.iterdir()) == []  # no spool, no asammdf temporary file, no .partial.mf4
    assert not list(tmp_path.rglob("*.mf4"))


def test_a_recording_deleted_behind_the_service_is_missing_without_its_path(
    storage, tmp_path
):  # on SQLite and PostgreSQL (tests/conftest.py)
    store = RecordingStore(
        storage, tmp_path / "recordings", keep_gb=1.0, sample_rate_hz=RATE_HZ, accel_full_scale_rad_s2=FULL_SCALE
    )
    [rid] = _stored_results(storage, 1)
    storage.set_result_recording(rid, {"format": "mf4", "path": str(store.path(rid)), "bytes": 10})
    with pytest.raises(RecordingUnavailable) as exc:
        store.open(rid)
    assert f"result {rid} is missing" in str(exc.value) and str(tmp_path) not in str(exc.value)
