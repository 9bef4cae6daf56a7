"""Storage migrations, per-point transactions, map assembly and LUT export (C header compiled by gcc)."""
import csv
import io
import json
import math
import shutil
import sqlite3
import subprocess

import pytest

from service import __version__
from service.public import result_row
from service.identification.adaptive import AdaptiveOptions
from service.identification.result import IdentificationResult
from service.harmonic import Phasor
from service.lut_export import export_map
from service.maps import build_map_from_sweep
from service.public import map_public
from service.operating_point import OperatingPoint
from service.storage import Storage, StorageError, migrations


def _result(gamma_deg, delta_deg):
    tc = math.radians(gamma_deg) * math.cos(math.radians(delta_deg))
    ts = -math.radians(gamma_deg) * math.sin(math.radians(delta_deg))
    return IdentificationResult("adaptive", 6, "ok", tc, ts, Phasor(1e-4, 0, 100, 6), Phasor(0.07, 0.01, 100, 6), 0.5, 8)


@pytest.fixture
def storage(tmp_path):
    return Storage(tmp_path / "r.db")


def test_migrations_set_user_version_and_are_idempotent(storage):
    with sqlite3.connect(storage.path) as conn:
        assert conn.execute("PRAGMA user_version").fetchone()[0] == len(migrations())
    assert storage.migrate() == len(migrations())


def test_newer_database_is_refused(tmp_path):
    path = tmp_path / "new.db"
    with sqlite3.connect(path) as conn:
        conn.execute("PRAGMA user_version = 999")
    with pytest.raises(StorageError, match="newer than this software"):
        Storage(path)


def test_tokens_are_stored_hashed(storage):
    token_id, token = storage.create_token("operator")
    assert storage.token_role(token) == "operator"
    with sqlite3.connect(storage.path) as conn:
        assert token not in str(conn.execute("SELECT * FROM api_tokens").fetchall())
    assert storage.revoke_token(token_id)
    assert storage.token_role(token) is None


def _sweep_with_results(storage, failing=()):
    grid = {"torque_nm": [1.0, 2.5], "speed_rpm": [1000.0, 2000.0], "udc_v": [12.0]}
    sweep_id = storage.create_sweep("adaptive", 6, grid, {}, 4, "test-bench", __version__)
    for i, (t, n) in enumerate([(1.0, 1000.0), (2.5, 1000.0), (1.0, 2000.0), (2.5, 2000.0)]):
        op = OperatingPoint(torque_nm=t, speed_rpm=n, udc_v=12.0)
        if (t, n) in failing:
            row = result_row(op, "adaptive", AdaptiveOptions(), "test-bench", "t0", error="MeasurementError: boom", sweep_id=sweep_id)
        else:
            row = result_row(op, "adaptive", AdaptiveOptions(), "test-bench", "t0", _result(1 + i, 250 + 10 * i), sweep_id=sweep_id)
        storage.insert_result(row)
    return sweep_id


def test_failed_point_keeps_the_others(storage):
    sweep_id = _sweep_with_results(storage, failing={(2.5, 1000.0)})
    rows = storage.sweep_results(sweep_id)
    assert [r["status"] for r in rows] == ["ok", "failed", "ok", "ok"]
    assert storage.get_sweep(sweep_id)["done_points"] == 4
    m = map_public(storage, build_map_from_sweep(storage, sweep_id)).model_dump()
    bad = [c for c in m["cells"] if c["status"] == "failed"]
    assert len(bad) == 1 and bad[0]["theta_cos"] is None and "boom" in bad[0]["error"]


def test_csv_export_carries_axes_units_order_version(storage):
    m = map_public(storage, build_map_from_sweep(storage, _sweep_with_results(storage))).model_dump()
    text = export_map(m, "csv")
    header = "".join(line for line in text.splitlines(True) if line.startswith("#"))
    assert "harmonic order h = 6" in header and __version__ in header and "speed_rpm = [1000.0, 2000.0]" in header
    rows = list(csv.DictReader(io.StringIO("".join(l for l in text.splitlines(True) if not l.startswith("#")))))
    assert len(rows) == 4
    first = rows[0]
    assert float(first["gamma_deg"]) == pytest.approx(1.0) and float(first["delta_deg"]) == pytest.approx(250.0)
    assert math.hypot(float(first["theta_cos_rad"]), float(first["theta_sin_rad"])) == pytest.approx(math.radians(1.0))


def test_json_export_indexes_udc_speed_torque(storage):
    m = map_public(storage, build_map_from_sweep(storage, _sweep_with_results(storage))).model_dump()
    doc = json.loads(export_map(m, "json"))
    assert doc["index_order"] == ["udc_v", "speed_rpm", "torque_nm"] and doc["harmonic_order"] == 6
    # cell (udc 12, speed 2000, torque 2.5) was the 4th result: gamma 4 deg, delta 280 deg
    tc, ts = doc["theta_cos_rad"][0][1][1], doc["theta_sin_rad"][0][1][1]
    assert math.degrees(math.hypot(tc, ts)) == pytest.approx(4.0)
    assert math.degrees(-math.atan2(ts, tc)) % 360 == pytest.approx(280.0)


@pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc not installed")
def test_c_header_compiles_and_holds_the_values(storage, tmp_path):
    m = map_public(storage, build_map_from_sweep(storage, _sweep_with_results(storage, failing={(1.0, 2000.0)}))).model_dump()
    (tmp_path / "lut.h").write_text(export_map(m, "c"))
    (tmp_path / "main.c").write_text(
        '#include <stdio.h>\n#include <math.h>\n#include "lut.h"\n'
        "int main(void){ float tc = ripplecal_lut_theta_cos_rad[0][1][1], ts = ripplecal_lut_theta_sin_rad[0][1][1];\n"
        ' printf("%u %u %u %u %s %.4f %d\\n", RIPPLECAL_LUT_HARMONIC_ORDER, RIPPLECAL_LUT_N_TORQUE, RIPPLECAL_LUT_N_SPEED,\n'
        "  RIPPLECAL_LUT_N_UDC, RIPPLECAL_LUT_SOFTWARE_VERSION, sqrtf(tc*tc+ts*ts)*57.29578f, ripplecal_lut_valid[0][1][0]);\n"
        " return 0; }\n")
    subprocess.run(["gcc", "-std=c99", "-Wall", "-Werror", "-o", str(tmp_path / "lut"), str(tmp_path / "main.c"), "-lm"],
                   check=True, cwd=tmp_path)
    out = subprocess.run([str(tmp_path / "lut")], capture_output=True, text=True, check=True).stdout.split()
    assert out[:4] == ["6", "2", "2", "1"] and out[4] == __version__
    assert float(out[5]) == pytest.approx(4.0, abs=1e-3)
    assert out[6] == "0"   # the failed cell is marked invalid


def test_dcm_export_has_one_map_per_component(storage):
    m = map_public(storage, build_map_from_sweep(storage, _sweep_with_results(storage))).model_dump()
    text = export_map(m, "dcm")
    assert "KONSERVIERUNG_FORMAT 2.0" in text
    assert text.count("KENNFELD ") == 3 and text.count("END") == 3
    assert "ST/X   1   2.5" in text and __version__ in text


def test_lut_image_is_what_the_drive_parses(storage):
    """The service's image against the codec the drive firmware decodes with (drivers.lut_image)."""
    import zlib

    from drivers.lut_image import LutImageError
    from drivers.lut_image import decode as parse
    from service.lut_export import lut_image
    m = map_public(storage, build_map_from_sweep(storage, _sweep_with_results(storage, failing={(1.0, 2000.0)}))).model_dump()
    image = lut_image(m)
    lut = parse(image)
    assert lut.crc == zlib.crc32(image) and lut.harmonic_order == 6
    assert list(lut.torque_nm) == [1.0, 2.5] and list(lut.speed_rpm) == [1000.0, 2000.0]
    tc, ts = lut.theta(2.5, 2000.0, 12.0)             # grid point: the 4th result, gamma 4 deg, delta 280 deg
    assert math.degrees(math.hypot(tc, ts)) == pytest.approx(4.0, rel=1e-6)
    assert not lut.valid[0, 1, 0]
    bad = bytearray(image)
    bad[40] ^= 0x01
    with pytest.raises(LutImageError):
        parse(bytes(bad))
