"""LUT export for firmware: CSV, JSON and a C header, each carrying the axes, units, harmonic order
and software version. Values are stored as theta = (theta_cos, theta_sin) in rad, the space in
which the drive interpolates (never across the 0/360 deg wrap of delta); gamma/delta in degrees
are given for reading. Cells without a valid result export theta = 0 (no injection) and valid = 0."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import csv
import io
import json
import re

from drivers import lut_image as lut_codec
from service import __version__, map_quality



def _grid_values(m: dict, key: str) -> list[list[list[float]]]:
    """[udc][speed][torque] array of a cell field (0 where the cell is not ok)."""
    axes = m["axes"]
    by_op = {(c["torque_nm"], c["speed_rpm"], c["udc_v"]): c for c in m["cells"]}
    out = []
    for u in axes["udc_v"]:
        plane = []
        for n in axes["speed_rpm"]:
            row = []
            for t in axes["torque_nm"]:
                c = by_op.get((t, n, u))
                ok = c is not None and c["status"] == "ok"
                row.append((1.0 if ok else 0.0) if key == "valid" else (c[key] if ok else 0.0))
            plane.append(row)
        out.append(plane)
    return out


def _counts_text(m: dict) -> str:
    counts = m.get("status_counts") or {}
    return ", ".join(f"{n} {status}" for status, n in counts.items() if n) or "none"


def _quality_text(m: dict) -> str:
    """One comment line: the map's outlier and smoothed cells (GET /maps/{id} has each reason)."""
    q = m.get("quality") or {}

    def where(quality: str) -> str:
        cells = [f"{c['torque_nm']:g} Nm / {c['speed_rpm']:g} rpm / {c['udc_v']:g} V" for c in m["cells"]
                 if c.get("quality") == quality]
        return f" ({'; '.join(cells)})" if cells else ""
    text = (f"quality: {q.get('outliers', 0)} outlier(s){where('outlier')}, {q.get('unchecked', 0)} unchecked, "
            f"theta against the median of its ok neighbours, outlier beyond {q.get('outlier_factor', 0):g}x the expected step")
    if m.get("smoothed"):
        text += f"; SMOOTHED view: {q.get('smoothed', 0)} outlier cell(s) carry their neighbours' median theta{where('smoothed')}"
    return text


def _quality_json(m: dict) -> dict:
    marked = [{key: c.get(key) for key in ("torque_nm", "speed_rpm", "udc_v", *map_quality.CELL_FIELDS)}
              for c in m["cells"] if c.get("quality") in ("outlier", "smoothed")]
    return {**(m.get("quality") or {}), "smoothed_view": bool(m.get("smoothed")), "cells": marked}


def _validation_text(m: dict) -> str:
    """The latest validation in the drive's LUT mode, one line (every export carries it)."""
    v = m.get("validation")
    if not v:
        return "not validated in the drive's LUT mode"

    def part(kind: str) -> str:
        k = v[kind]
        if k["median_db"] is None:
            return f"{kind} none measured of {k['cells']}"
        return (f"{kind} median {k['median_db']:.1f} dB, min {k['min_db']:.1f} dB "
                f"({k['measured']} of {k['cells']} measured)")
    worst = v.get("worst")
    where = "" if not worst else (f"; worst {worst['suppression_db']:.1f} dB at {worst['operating_point']['torque_nm']:g} Nm, "
                                  f"{worst['operating_point']['speed_rpm']:g} rpm, {worst['operating_point']['udc_v']:g} V "
                                  f"({worst['kind']})")
    return (f"validated in the drive's LUT mode (job {v['job_id']}, {v['finished_at']}, {v['state']}): "
            f"{part('grid')}; {part('midpoint')}{where}")


def export_csv(m: dict) -> str:
    buf = io.StringIO()
    buf.write(f"# ripplecal LUT, map {m['id']}, harmonic order h = {m['harmonic_order']}, method {m['method']}\n")
    buf.write(f"# software version {__version__}, bench {m['bench_identity']}, created {m['created_at']}\n")
    buf.write(f"# axes: torque_nm = {m['axes']['torque_nm']}, speed_rpm = {m['axes']['speed_rpm']}, udc_v = {m['axes']['udc_v']}\n")
    buf.write("# v_inj = theta_cos*cos(h*phi_e) + theta_sin*sin(h*phi_e) = gamma*cos(h*phi_e + delta); theta in rad\n")
    buf.write(f"# cells: {_counts_text(m)}; only ok cells carry theta (valid), the others are 0\n")
    buf.write(f"# {_quality_text(m)}\n")
    buf.write(f"# {_validation_text(m)}\n")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["torque_nm", "speed_rpm", "udc_v", "theta_cos_rad", "theta_sin_rad", "gamma_deg", "delta_deg",
                "suppression_db", "status"])
    for c in m["cells"]:
        ok = c["status"] == "ok"
        w.writerow([c["torque_nm"], c["speed_rpm"], c["udc_v"],
                    repr(c["theta_cos"]) if ok else 0.0, repr(c["theta_sin"]) if ok else 0.0,
                    c["gamma_deg"] if ok else "", c["delta_deg"] if ok else "",
                    "" if c["suppression_db"] is None else round(c["suppression_db"], 2), c["status"]])
    return buf.getvalue()


def export_json(m: dict) -> str:
    return json.dumps({
        "format": "ripplecal-lut", "format_version": 1, "software_version": __version__,
        "map_id": m["id"], "harmonic_order": m["harmonic_order"], "method": m["method"],
        "bench": m["bench_identity"], "created_at": m["created_at"],
        "units": {"torque": "Nm", "speed": "rpm (mechanical)", "udc": "V", "theta": "rad"},
        "axes": m["axes"], "index_order": ["udc_v", "speed_rpm", "torque_nm"],
        "theta_cos_rad": _grid_values(m, "theta_cos"), "theta_sin_rad": _grid_values(m, "theta_sin"),
        "valid": _grid_values(m, "valid"), "status_counts": m.get("status_counts"),
        "cells": [{k: v for k, v in c.items() if k not in map_quality.CELL_FIELDS} for c in m["cells"]],
        "quality": _quality_json(m),
        "validation": m.get("validation"),
    }, indent=1)


def _c_array(values) -> str:
    if isinstance(values, list) and values and isinstance(values[0], list):
        return "{" + ", ".join(_c_array(v) for v in values) + "}"
    return "{" + ", ".join(_c_float(v) for v in values) + "}"


def _c_float(value: float) -> str:
    text = f"{float(value):.9g}"
    if not any(ch in text for ch in ".en"):
        text += ".0"            # "0f" is not a C literal; "0.0f" is
    return text + "f"


def export_c(m: dict) -> str:
    nt, nn, nu = (len(m["axes"][k]) for k in ("torque_nm", "speed_rpm", "udc_v"))
    # every name carries the map id, so the headers of several maps go into one translation unit
    macro, array = f"RIPPLECAL_LUT_MAP{int(m['id'])}", f"ripplecal_lut_map{int(m['id'])}"
    guard = f"{macro}_H"
    version = re.sub(r"[^0-9A-Za-z.+-]", "", __version__)
    valid = [[[int(v) for v in row] for row in plane] for plane in _grid_values(m, "valid")]
    lines = [
        f"/* ripplecal LUT for harmonic injection: map {m['id']}, method {m['method']}.",
        f" * Bench: {m['bench_identity']}; created {m['created_at']}; software version {version}.",
        " * v_inj = theta_cos*cos(h*phi_e) + theta_sin*sin(h*phi_e)  [rad], applied as a voltage-angle",
        " * rotation (|u_dq*| = |u_dq|). Interpolate theta_cos and theta_sin (never gamma/delta across",
        " * the 0/360 deg wrap). Index order [udc][speed][torque]; cells with valid == 0 carry no injection.",
        f" * Cells: {_counts_text(m)}. Names carry the map id ({macro}_*, {array}_*).",
        f" * {_quality_text(m)}.",
        f" * {_validation_text(m)}.",
        " */",
        f"#ifndef {guard}", f"#define {guard}", "",
        "#include <stdint.h>", "",
        f"#define {macro}_ID {int(m['id'])}u",
        f'#define {macro}_SOFTWARE_VERSION "{version}"',
        f"#define {macro}_HARMONIC_ORDER {int(m['harmonic_order'])}u",
        f"#define {macro}_N_TORQUE {nt}u",
        f"#define {macro}_N_SPEED {nn}u",
        f"#define {macro}_N_UDC {nu}u", "",
        f"/* torque axis, Nm */\nstatic const float {array}_torque_nm[{nt}] = {_c_array(m['axes']['torque_nm'])};",
        f"/* speed axis, rpm (mechanical) */\nstatic const float {array}_speed_rpm[{nn}] = {_c_array(m['axes']['speed_rpm'])};",
        f"/* DC-link voltage axis, V */\nstatic const float {array}_udc_v[{nu}] = {_c_array(m['axes']['udc_v'])};", "",
        f"/* theta_cos, rad */\nstatic const float {array}_theta_cos_rad[{nu}][{nn}][{nt}] = {_c_array(_grid_values(m, 'theta_cos'))};",
        f"/* theta_sin, rad */\nstatic const float {array}_theta_sin_rad[{nu}][{nn}][{nt}] = {_c_array(_grid_values(m, 'theta_sin'))};",
        f"/* 1 where the cell holds an identified value */\nstatic const uint8_t {array}_valid[{nu}][{nn}][{nt}] = "
        + "{" + ", ".join("{" + ", ".join("{" + ", ".join(str(v) for v in row) + "}" for row in plane) + "}" for plane in valid) + "};",
        "", f"#endif /* {guard} */", "",
    ]
    return "\n".join(lines)


def export_dcm(m: dict) -> str:
    """DCM 2.0 (calibration data exchange format read by INCA / CANape): one KENNFELD per U_dc and
    theta component, x = torque (Nm), y = speed (rpm)."""
    axes = m["axes"]
    nt, nn = len(axes["torque_nm"]), len(axes["speed_rpm"])
    out = [f"* ripplecal LUT, map {m['id']}, harmonic order h = {m['harmonic_order']}, method {m['method']}",
           f"* software version {__version__}, bench {m['bench_identity']}, created {m['created_at']}",
           f"* cells: {_counts_text(m)}; VALID = 1 only where the result met its target (ok)",
           f"* {_quality_text(m)}",
           f"* {_validation_text(m)}",
           "KONSERVIERUNG_FORMAT 2.0", ""]
    for name, key in (("THETA_COS", "theta_cos"), ("THETA_SIN", "theta_sin"), ("VALID", "valid")):
        for k, udc in enumerate(axes["udc_v"]):
            plane = _grid_values(m, key)[k]
            out += [f"KENNFELD RIPPLECAL_H{m['harmonic_order']}_{name}_U{udc:g}V".replace(".", "P") + f" {nt} {nn}",
                    f'   LANGNAME "{name.lower()} at U_dc = {udc:g} V"',
                    '   EINHEIT_X "Nm"', '   EINHEIT_Y "rpm"', f'   EINHEIT_W "{"-" if key == "valid" else "rad"}"',
                    "   ST/X   " + "   ".join(f"{t:g}" for t in axes["torque_nm"])]
            for j, speed in enumerate(axes["speed_rpm"]):
                out += [f"   ST/Y   {speed:g}", "   WERT   " + "   ".join(f"{v:.9g}" for v in plane[j])]
            out += ["END", ""]
    return "\n".join(out)


def lut_image(m: dict) -> bytes:
    """The binary image the drive takes on 0x2001:1, carrying the map's id (docs/interfaces.md, "LUT
    image"; encoded by drivers.lut_image, the one definition the drive firmware decodes with). Raises
    ValueError if the map cannot become an image (too many cells, an axis not strictly increasing)."""
    axes = m["axes"]
    return lut_codec.encode(m["harmonic_order"], *(axes[key] for key in lut_codec.AXES),
                            _grid_values(m, "theta_cos"), _grid_values(m, "theta_sin"),
                            valid=_grid_values(m, "valid"), map_id=m["id"])


@dataclass(frozen=True)
class ExportFormat:
    name: str
    display_name: str
    media_type: str
    extension: str
    render: Callable[[dict], str]


# the one registry of export formats: the API's `format` parameter, the CLI's choices and the
# dashboard (GET /api/v1/export-formats) read it
EXPORT_FORMATS: dict[str, ExportFormat] = {f.name: f for f in (
    ExportFormat("csv", "CSV", "text/csv", "csv", export_csv),
    ExportFormat("json", "JSON", "application/json", "json", export_json),
    ExportFormat("c", "C header", "text/x-csrc", "h", export_c),
    ExportFormat("dcm", "DCM (INCA / CANape)", "text/plain", "dcm", export_dcm),
)}


def export_map(m: dict, fmt: str) -> str:
    if fmt not in EXPORT_FORMATS:
        raise ValueError(f"format {fmt!r} is not supported; choose one of {sorted(EXPORT_FORMATS)}")
    return EXPORT_FORMATS[fmt].render(m)
