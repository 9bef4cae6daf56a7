"""Storage migrations, per-point transactions, map assembly and LUT export (C headers compiled by gcc,
DCM read by dcmReader)."""

import csv
import io
import json
import logging
import math
import shutil
import sqlite3
import subprocess

import pytest

from service import __version__
from service.api.public.maps import map_public
from service.maps.build import build_map_from_sweep
from service.maps.lut_export import export_map
from service.store.migrations import migration_files
from service.store.storage import Storage, StorageError
from tests.support.stored_maps import sweep_with_results

# `storage` (tests/conftest.py): every test here runs on SQLite and on PostgreSQL


def test_migrations_are_idempotent(storage):
    assert storage.migrate() == len(migration_files())
    assert storage.migrate() == len(migration_files())


def test_migrations_set_user_version_on_sqlite(tmp_path):
    storage = Storage(tmp_path / "r.db")
    with sqlite3.connect(storage.path) as conn:
        assert conn.execute("PRAGMA user_version").fetchone()[0] == len(migration_files())


def test_newer_database_is_refused(tmp_path):
    path = tmp_path / "new.db"
    with sqlite3.connect(path) as conn:
        conn.execute("PRAGMA user_version = 999")
    with pytest.raises(StorageError, match="newer than this software"):
        Storage(path)


def test_tokens_are_stored_hashed(storage):
    token_id, token = storage.create_token("operator")
    assert storage.token_role(token) == "operator"
    with storage.connect() as conn:
        assert token not in str([tuple(r) for r in conn.execute("SELECT * FROM api_tokens").fetchall()])
    assert storage.revoke_token(token_id)
    assert storage.token_role(token) is None


def test_failed_point_keeps_the_others(storage):
    sweep_id = sweep_with_results(storage, failing={(2.5, 1000.0)})
    rows = storage.sweep_results(sweep_id)
    assert [r["status"] for r in rows] == ["ok", "failed", "ok", "ok"]
    assert storage.get_sweep(sweep_id)["done_points"] == 4
    m = map_public(storage, build_map_from_sweep(storage, sweep_id)).model_dump()
    bad = [c for c in m["cells"] if c["status"] == "failed"]
    assert len(bad) == 1 and "boom" in bad[0]["error"]
    # its LUT entry is the fill rule's (held from an ok neighbour on its lines), flagged, never ok
    assert bad[0]["filled"] and bad[0]["fill_source"].startswith(("held", "interpolated"))
    assert bad[0]["theta_cos"] is not None and m["filled_cells"] == 1


def test_csv_export_carries_axes_units_order_version(storage):
    m = map_public(storage, build_map_from_sweep(storage, sweep_with_results(storage))).model_dump()
    text = export_map(m, "csv")
    header = "".join(line for line in text.splitlines(True) if line.startswith("#"))
    assert "harmonic order h = 6" in header and __version__ in header and "speed_rpm = [1000.0, 2000.0]" in header
    rows = list(csv.DictReader(io.StringIO("".join(l for l in text.splitlines(True) if not l.startswith("#")))))
    assert len(rows) == 4
    first = rows[0]
    assert float(first["gamma_deg"]) == pytest.approx(1.0) and float(first["delta_deg"]) == pytest.approx(250.0)
    assert math.hypot(float(first["theta_cos_rad"]), float(first["theta_sin_rad"])) == pytest.approx(math.radians(1.0))


def test_json_export_indexes_udc_speed_torque(storage):
    m = map_public(storage, build_map_from_sweep(storage, sweep_with_results(storage))).model_dump()
    doc = json.loads(export_map(m, "json"))
    assert doc["index_order"] == ["udc_v", "speed_rpm", "torque_nm"] and doc["harmonic_order"] == 6
    # cell (udc 12, speed 2000, torque 2.5) was the 4th result: gamma 4 deg, delta 280 deg
    tc, ts = doc["theta_cos_rad"][0][1][1], doc["theta_sin_rad"][0][1][1]
    assert math.degrees(math.hypot(tc, ts)) == pytest.approx(4.0)
    assert math.degrees(-math.atan2(ts, tc)) % 360 == pytest.approx(280.0)


NO_GCC = "gcc is not on PATH: the exported C headers cannot be compiled here"


@pytest.mark.skipif(shutil.which("gcc") is None, reason=NO_GCC)
def test_c_header_compiles_and_holds_the_values(storage, tmp_path):
    m = map_public(
        storage, build_map_from_sweep(storage, sweep_with_results(storage, failing={(1.0, 2000.0)}))
    ).model_dump()
    n = m["id"]
    (tmp_path / "lut.h").write_text(export_map(m, "c"))
    (tmp_path / "main.c").write_text(
        '#include <stdio.h>\n#include <math.h>\n#include "lut.h"\n'
        f"int main(void){{ float tc = ripplecal_lut_map{n}_theta_cos_rad[0][1][1], ts = ripplecal_lut_map{n}_theta_sin_rad[0][1][1];\n"
        f' printf("%u %u %u %u %u %s %.4f %d\\n", RIPPLECAL_LUT_MAP{n}_ID, RIPPLECAL_LUT_MAP{n}_HARMONIC_ORDER,\n'
        f"  RIPPLECAL_LUT_MAP{n}_N_TORQUE, RIPPLECAL_LUT_MAP{n}_N_SPEED, RIPPLECAL_LUT_MAP{n}_N_UDC,\n"
        f"  RIPPLECAL_LUT_MAP{n}_SOFTWARE_VERSION, sqrtf(tc*tc+ts*ts)*57.29578f, ripplecal_lut_map{n}_valid[0][1][0]);\n"
        " return 0; }\n"
    )
    subprocess.run(
        ["gcc", "-std=c99", "-Wall", "-Werror", "-o", str(tmp_path / "lut"), str(tmp_path / "main.c"), "-lm"],
        check=True,
        cwd=tmp_path,
    )
    out = subprocess.run([str(tmp_path / "lut")], capture_output=True, text=True, check=True).stdout.split()
    assert out[:5] == [str(n), "6", "2", "2", "1"] and out[5] == __version__
    assert float(out[6]) == pytest.approx(4.0, abs=1e-3)
    assert out[7] == "0"  # the failed cell is marked invalid


@pytest.mark.skipif(shutil.which("gcc") is None, reason=NO_GCC)
def test_two_maps_c_headers_go_into_one_translation_unit(storage, tmp_path):
    """Every macro and array name carries the map id: two headers, one .c file, -Wall -Werror."""
    a = map_public(storage, build_map_from_sweep(storage, sweep_with_results(storage))).model_dump()
    b = map_public(
        storage, build_map_from_sweep(storage, sweep_with_results(storage, failing={(2.5, 1000.0)}))
    ).model_dump()
    assert a["id"] != b["id"]
    for m in (a, b):
        (tmp_path / f"map{m['id']}.h").write_text(export_map(m, "c"))
    i, j = a["id"], b["id"]
    (tmp_path / "both.c").write_text(
        f'#include <stdio.h>\n#include "map{i}.h"\n#include "map{j}.h"\n#include "map{i}.h"\n'  # guards hold too
        f'int main(void){{ printf("%u %u %d %d %.6f %.6f\\n", RIPPLECAL_LUT_MAP{i}_ID, RIPPLECAL_LUT_MAP{j}_ID,\n'
        f"  ripplecal_lut_map{i}_valid[0][0][1], ripplecal_lut_map{j}_valid[0][0][1],\n"
        f"  ripplecal_lut_map{i}_theta_cos_rad[0][1][1], ripplecal_lut_map{j}_theta_cos_rad[0][1][1]); return 0; }}\n"
    )
    subprocess.run(
        ["gcc", "-std=c99", "-Wall", "-Werror", "-o", str(tmp_path / "both"), str(tmp_path / "both.c")],
        check=True,
        cwd=tmp_path,
        capture_output=True,
        text=True,
    )
    out = subprocess.run([str(tmp_path / "both")], capture_output=True, text=True, check=True).stdout.split()
    assert out[:4] == [str(i), str(j), "1", "0"]  # (2.5 Nm, 1000 rpm) failed in map b only
    assert (
        float(out[4]) == pytest.approx(float(out[5]), abs=1e-6) == pytest.approx(a["cells"][3]["theta_cos"], abs=1e-6)
    )


def test_dcm_export_has_one_map_per_component(storage):
    m = map_public(storage, build_map_from_sweep(storage, sweep_with_results(storage))).model_dump()
    text = export_map(m, "dcm")
    assert "KONSERVIERUNG_FORMAT 2.0" in text
    # THETA_COS, THETA_SIN, VALID, FILLED, INJECTION_OFF
    assert text.count("KENNFELD ") == 5 and text.count("END") == 5
    assert "ST/X   1   2.5" in text and __version__ in text


def test_dcm_export_reads_in_dcmreader_with_valid_0_where_a_cell_is_not_ok(storage, tmp_path, caplog):
    """dcmReader (the DCM parser of the calibration tools' users) reads the five KENNFELDs with their
    axes; VALID is 0 exactly at the cell that failed; THETA there is its fill if the map carries one
    (FILLED = 1), else 0 (no injection)."""
    from dcmReader.dcm_reader import DcmReader

    m = map_public(
        storage, build_map_from_sweep(storage, sweep_with_results(storage, failing={(1.0, 2000.0)}))
    ).model_dump()
    path = tmp_path / "lut.dcm"
    path.write_text(export_map(m, "dcm"))
    reader = DcmReader()
    with caplog.at_level(logging.WARNING, logger="dcmReader"):
        reader.read(str(path))
    assert not [r for r in caplog.records if r.name.startswith("dcmReader")], caplog.text  # no dimension errors
    maps = {k.name: k for k in reader.get_characteristic_maps()}
    assert set(maps) == {
        "RIPPLECAL_H6_THETA_COS_U12V",
        "RIPPLECAL_H6_THETA_SIN_U12V",
        "RIPPLECAL_H6_VALID_U12V",
        "RIPPLECAL_H6_FILLED_U12V",
        "RIPPLECAL_H6_INJECTION_OFF_U12V",
    }
    valid = maps["RIPPLECAL_H6_VALID_U12V"]
    assert (valid.x_dimension, valid.y_dimension, valid.unit_x, valid.unit_y) == (2, 2, "Nm", "rpm")
    # values[speed][torque]
    assert valid.values == {1000: {1: 1, 2.5: 1}, 2000: {1: 0, 2.5: 1}}
    cells = {(c["torque_nm"], c["speed_rpm"]): c for c in m["cells"]}
    for (t, n), c in cells.items():
        theta = maps["RIPPLECAL_H6_THETA_COS_U12V"].values[n][t]
        carried = c["status"] == "ok" or c.get("filled")
        assert theta == (pytest.approx(c["theta_cos"], rel=1e-7) if carried else 0)
        assert maps["RIPPLECAL_H6_FILLED_U12V"].values[n][t] == (1 if c.get("filled") else 0)
    assert cells[(1.0, 2000.0)]["status"] == "failed"


def test_lut_image_is_what_the_drive_parses(storage):
    """The service's image against the codec the drive firmware decodes with (drivers.lut_image)."""
    import zlib

    from drivers.lut_image import LutImageError
    from drivers.lut_image import decode as parse
    from service.maps.lut_export import lut_image

    m = map_public(
        storage, build_map_from_sweep(storage, sweep_with_results(storage, failing={(1.0, 2000.0)}))
    ).model_dump()
    image = lut_image(m)
    lut = parse(image)
    assert lut.crc == zlib.crc32(image[:-4]) and lut.harmonic_order == 6 and lut.map_id == m["id"]
    assert list(lut.torque_nm) == [1.0, 2.5] and list(lut.speed_rpm) == [1000.0, 2000.0]
    tc, ts = lut.theta(2.5, 2000.0, 12.0)  # grid point: the 4th result, gamma 4 deg, delta 280 deg
    assert math.degrees(math.hypot(tc, ts)) == pytest.approx(4.0, rel=1e-6)
    assert not lut.valid[0, 1, 0]
    bad = bytearray(image)
    bad[40] ^= 0x01
    with pytest.raises(LutImageError):
        parse(bytes(bad))
