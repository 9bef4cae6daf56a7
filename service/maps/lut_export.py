"""LUT export for firmware: CSV, JSON, a C header and DCM, each carrying the axes, units, harmonic
order and software version. Values are stored as theta = (theta_cos, theta_sin) in rad; gamma/delta
in degrees are given for reading. The drive interpolates by the mode in the LUT image's header
(drivers/lut_image.py: cartesian theta or polar gamma/delta along the shortest arc; each export names
the mode a download would use). Each axis carries its own strictly increasing breakpoints (non-uniform
spacing allowed: the drive interpolates by position).

Cells: `ok` cells carry their result's theta (VALID = 1). A filled cell (status not ok, `filled`: the
fill rule of service/maps/fill.py) carries its fill, flagged FILLED = 1 and VALID = 0 in every export:
exports always show the fill, only a LUT download chooses whether it goes into the drive (`fill`).
A cell with injection off (`injection_off`, set on the stored map: Storage.set_injection_off) is flagged
INJECTION_OFF = 1 (VALID = 0, FILLED = 0) and carries its theta for the record where it has one; the
drive injects nothing in any interval that has it as a corner of non-zero weight (LUT flag 3, image
format_version 4: drivers/lut_image.py), so there it gives exactly no compensation, never worse.
Every other cell exports theta = 0 (no injection), VALID = 0, FILLED = 0, INJECTION_OFF = 0.
The C header also carries the drive's interpolation in C (`ripplecal_lut_map<ID>_theta`: Lut.theta, then the
clamp to gamma_max), for firmware to use as is."""

from __future__ import annotations

import csv
import io
import json
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Callable, cast

import numpy as np

from drivers import lut_image as lut_codec
from drivers.lut_image import Interpolation as Interpolation  # the request field, for the layers above
from service import __version__
from service.maps import quality as map_quality
from service.maps.view import order_map

# 2: `filled` grid and cell fields, `interpolation`, `lut_format_version`; 3: `injection_off` grid and cell field;
# 4: `orders` and, for a map of several orders, `further_orders` (each order's grids, counts and cells)
JSON_FORMAT_VERSION = 4


def map_orders(m: dict[str, Any]) -> list[int]:
    """The harmonic orders of a map (MapView.model_dump()), its own first."""
    return list(m.get("orders") or [m["harmonic_order"]])


def order_maps(m: dict[str, Any]) -> list[dict[str, Any]]:
    """The map as one map of one order per order (service/maps/view.py order_map), its own first."""
    return [order_map(m, h) for h in map_orders(m)]


def cell_flag(c: dict[str, Any] | None, fill: bool = True) -> int:
    """The LUT flag of a map cell: FLAG_OFF where injection is off (before anything else), FLAG_OK for
    ok, FLAG_FILLED for a filled cell that carries theta (only with `fill`), FLAG_NONE otherwise (no
    entry: the drive injects nothing there)."""
    if c is None:
        return lut_codec.FLAG_NONE
    if c.get("injection_off"):
        return lut_codec.FLAG_OFF
    if c["status"] == "ok":
        return lut_codec.FLAG_OK
    if fill and c.get("filled") and c.get("theta_cos") is not None and c.get("theta_sin") is not None:
        return lut_codec.FLAG_FILLED
    return lut_codec.FLAG_NONE


def grid_values(m: dict[str, Any], key: str, fill: bool = True) -> list[list[list[float]]]:
    """[udc][speed][torque] array of a cell field, or of its flag: key "flag" (0..3), "valid" (1 only
    for ok), "filled" (1 only where a fill is carried), "injection_off" (1 only where injection is off);
    theta is 0 where the cell has no entry (an off cell carries its theta where it has one)."""
    axes = m["axes"]
    by_op = {(c["torque_nm"], c["speed_rpm"], c["udc_v"]): c for c in m["cells"]}
    out: list[list[list[float]]] = []
    for u in axes["udc_v"]:
        plane: list[list[float]] = []
        for n in axes["speed_rpm"]:
            row: list[float] = []
            for t in axes["torque_nm"]:
                c = by_op.get((t, n, u))
                flag = cell_flag(c, fill)
                if key == "flag":
                    row.append(flag)
                elif key == "valid":
                    row.append(1 if flag == lut_codec.FLAG_OK else 0)
                elif key == "filled":
                    row.append(1 if flag == lut_codec.FLAG_FILLED else 0)
                elif key == "injection_off":
                    row.append(1 if flag == lut_codec.FLAG_OFF else 0)
                else:
                    row.append(_carried(c, flag, key))
            plane.append(row)
        out.append(plane)
    return out


def _carried(c: dict[str, Any] | None, flag: int, key: str) -> float:
    """A theta field as the LUT carries it: the cell's at an entry or an off cell that has one, else 0."""
    if c is None or flag == lut_codec.FLAG_NONE or c.get(key) is None:
        return 0.0
    return float(c[key])


def _has_theta(c: dict[str, Any], flag: int) -> bool:
    """The cell carries a theta in the exports (an entry, or an off cell with one for the record)."""
    return flag != lut_codec.FLAG_NONE and c.get("theta_cos") is not None and c.get("theta_sin") is not None


def _gamma_delta_deg(c: dict[str, Any]) -> tuple[float, float]:
    """gamma = |theta|, delta = -atan2(theta_sin, theta_cos) in [0, 360) deg (eq. 21-22)."""
    if c.get("gamma_deg") is not None and c.get("delta_deg") is not None:
        return c["gamma_deg"], c["delta_deg"]
    tc, ts = float(c["theta_cos"]), float(c["theta_sin"])
    return math.degrees(math.hypot(tc, ts)), math.degrees(-math.atan2(ts, tc)) % 360.0


def map_interpolation(m: dict[str, Any], interpolation: str | None = None) -> str:
    """The interpolation between cells a map's LUT is for: the one named, else the one the map was placed and
    validated in (a refinement records it in the map's provenance: a map refined in cartesian interpolation is
    downloaded and exported so, as its validation judged it), else the drive's default. LutImageError (a
    ValueError) for a name the drive does not know."""
    named = interpolation if interpolation is not None else (m.get("provenance") or {}).get("interpolation")
    return lut_codec.check_interpolation(named)


def interpolation_text(interpolation: str) -> str:
    return {
        "cartesian": "cartesian: theta_cos and theta_sin multilinear",
        "polar": "polar: gamma multilinear, delta multilinear along the shortest arc",
        "cubic": "cubic: a cubic Hermite of theta along speed in each row, then across torque (slopes from the "
        "neighbours), linear across U_dc",
    }[interpolation]


def _filled_text(m: dict[str, Any]) -> str:
    n = sum(1 for c in m["cells"] if cell_flag(c) == lut_codec.FLAG_FILLED)
    return f"{n} filled cell(s) (a LUT download takes them only with fill)" if n else "no filled cell"


def _off_cells(m: dict[str, Any]) -> int:
    return sum(1 for c in m["cells"] if cell_flag(c) == lut_codec.FLAG_OFF)


def _off_text(m: dict[str, Any]) -> str:
    n = _off_cells(m)
    if not n:
        return "no cell with injection off"
    return (
        f"{n} cell(s) with injection off (the drive injects nothing in any interval with one as a corner; "
        "their theta is kept for the record)"
    )


def cell_format(m: dict[str, Any]) -> str:
    """How the map's LUT image carries theta per cell: "float32" (9 bytes a cell), "int16" (5 bytes a cell, image
    version 5), "int11" (3 bytes a cell, version 6) or "int11-sparse" (3 bytes a stored cell, version 7), as the map
    was built for (its provenance's `lut_cells`,
    chosen by the refinement that built it)."""
    chosen = (m.get("provenance") or {}).get("lut_cells", "float32")
    return chosen if chosen in lut_codec.CELL_FORMATS else "float32"


def lut_format_version(m: dict[str, Any]) -> int:
    """The format_version of the map's LUT image: 5 with int16 cells, 6 with int11 cells, 7 with int11-sparse cells,
    else 4 with a cell whose injection is off, else 3."""
    return lut_codec.format_version_of([cell_flag(c) for c in m["cells"]], cell_format(m))


def _counts_text(m: dict[str, Any]) -> str:
    counts = m.get("status_counts") or {}
    return ", ".join(f"{n} {status}" for status, n in counts.items() if n) or "none"


def _quality_text(m: dict[str, Any]) -> str:
    """One comment line: the map's outlier and smoothed cells (GET /maps/{id} has each reason)."""
    q = m.get("quality") or {}

    def where(quality: str) -> str:
        cells = [
            f"{c['torque_nm']:g} Nm / {c['speed_rpm']:g} rpm / {c['udc_v']:g} V"
            for c in m["cells"]
            if c.get("quality") == quality
        ]
        return f" ({'; '.join(cells)})" if cells else ""

    text = (
        f"quality: {q.get('outliers', 0)} outlier(s){where('outlier')}, {q.get('unchecked', 0)} unchecked, "
        f"theta against the median of its ok neighbours, outlier beyond {q.get('outlier_factor', 0):g}x the expected step"
    )
    if m.get("smoothed"):
        text += f"; SMOOTHED view: {q.get('smoothed', 0)} outlier cell(s) carry their neighbours' median theta{where('smoothed')}"
    return text


def _quality_json(m: dict[str, Any]) -> dict[str, Any]:
    marked = [
        {key: c.get(key) for key in ("torque_nm", "speed_rpm", "udc_v", *map_quality.CELL_FIELDS)}
        for c in m["cells"]
        if c.get("quality") in ("outlier", "smoothed")
    ]
    return {**(m.get("quality") or {}), "smoothed_view": bool(m.get("smoothed")), "cells": marked}


def _validation_text(m: dict[str, Any]) -> str:
    """The latest validation in the drive's LUT mode, one line (every export carries it)."""
    v = m.get("validation")
    if not v:
        return "not validated in the drive's LUT mode"

    def part(kind: str) -> str:
        k = v[kind]
        if k["median_db"] is None:
            return f"{kind} none measured of {k['cells']}"
        return (
            f"{kind} median {k['median_db']:.1f} dB, min {k['min_db']:.1f} dB "
            f"({k['measured']} of {k['cells']} measured)"
        )

    worst = v.get("worst")
    where = (
        ""
        if not worst
        else (
            f"; worst {worst['suppression_db']:.1f} dB at {worst['operating_point']['torque_nm']:g} Nm, "
            f"{worst['operating_point']['speed_rpm']:g} rpm, {worst['operating_point']['udc_v']:g} V "
            f"({worst['kind']})"
        )
    )
    return (
        f"validated in the drive's LUT mode (job {v['job_id']}, {v['finished_at']}, {v['state']}): "
        f"{part('grid')}; {part('midpoint')}{where}"
    )


def export_csv(m: dict[str, Any], interpolation: str | None = None) -> str:
    """One row per cell; a map of several orders has one row per cell and order, and a last column
    harmonic_order (a map of one order keeps the columns it always had)."""
    mode = map_interpolation(m, interpolation)
    orders = map_orders(m)
    buf = io.StringIO()
    buf.write(f"# ripplecal LUT, map {m['id']}, harmonic order h = {m['harmonic_order']}, method {m['method']}\n")
    if m.get("partial"):
        buf.write(f"# PARTIAL: {m['partial']}\n")
    if len(orders) > 1:
        buf.write(
            f"# several orders: {', '.join(str(h) for h in orders)}, each cell once per order (column harmonic_order);"
            " the drive injects their sum, every theta scaled by one factor so that the sum of |theta| <= gamma_max\n"
        )
    buf.write(f"# software version {__version__}, bench {m['bench_identity']}, created {m['created_at']}\n")
    buf.write(
        f"# axes: torque_nm = {m['axes']['torque_nm']}, speed_rpm = {m['axes']['speed_rpm']}, udc_v = {m['axes']['udc_v']}\n"
    )
    buf.write("# v_inj = theta_cos*cos(h*phi_e) + theta_sin*sin(h*phi_e) = gamma*cos(h*phi_e + delta); theta in rad\n")
    buf.write(
        f"# cells: {_counts_text(m)}; ok cells carry their theta (valid), filled cells their fill "
        f"(filled = 1, not valid), the others 0; {_filled_text(m)}; {_off_text(m)}\n"
    )
    buf.write(f"# LUT interpolation: {interpolation_text(mode)} (LUT image format_version {lut_format_version(m)})\n")
    buf.write(f"# {_quality_text(m)}\n")
    buf.write(f"# {_validation_text(m)}\n")
    w = csv.writer(buf, lineterminator="\n")
    # filled, fill_source and injection_off last: readers of the columns before them by position keep working
    w.writerow(
        [
            "torque_nm",
            "speed_rpm",
            "udc_v",
            "theta_cos_rad",
            "theta_sin_rad",
            "gamma_deg",
            "delta_deg",
            "suppression_db",
            "status",
            "filled",
            "fill_source",
            "injection_off",
            *(["harmonic_order"] if len(orders) > 1 else []),
        ]
    )
    for h, c in ((om["harmonic_order"], c) for om in order_maps(m) for c in om["cells"]):
        flag = cell_flag(c)
        entry = _has_theta(c, flag)
        gamma, delta = _gamma_delta_deg(c) if entry else ("", "")
        w.writerow(
            [
                c["torque_nm"],
                c["speed_rpm"],
                c["udc_v"],
                repr(float(c["theta_cos"])) if entry else 0.0,
                repr(float(c["theta_sin"])) if entry else 0.0,
                gamma,
                delta,
                "" if c["suppression_db"] is None else round(c["suppression_db"], 2),
                c["status"],
                1 if flag == lut_codec.FLAG_FILLED else 0,
                (c.get("fill_source") or "") if flag == lut_codec.FLAG_FILLED else "",
                1 if flag == lut_codec.FLAG_OFF else 0,
                *([h] if len(orders) > 1 else []),
            ]
        )
    return buf.getvalue()


def export_json(m: dict[str, Any], interpolation: str | None = None) -> str:
    mode = map_interpolation(m, interpolation)
    return json.dumps(
        {
            "format": "ripplecal-lut",
            "format_version": JSON_FORMAT_VERSION,
            "software_version": __version__,
            "map_id": m["id"],
            "harmonic_order": m["harmonic_order"],
            "method": m["method"],
            "bench": m["bench_identity"],
            "created_at": m["created_at"],
            "units": {"torque": "Nm", "speed": "rpm (mechanical)", "udc": "V", "theta": "rad"},
            "axes": m["axes"],
            "index_order": ["udc_v", "speed_rpm", "torque_nm"],
            "interpolation": mode,
            "lut_format_version": lut_format_version(m),
            **_json_cells(m),
            "quality": _quality_json(m),
            "validation": m.get("validation"),
            "orders": map_orders(m),
            "further_orders": [_json_order(om) for om in order_maps(m)[1:]],
        },
        indent=1,
    )


def _json_order(m: dict[str, Any]) -> dict[str, Any]:
    """A further order of a map (order_map): its grids, counts and cells as the map's own are exported."""
    return {"harmonic_order": m["harmonic_order"], **_json_cells(m)}


def _json_cells(m: dict[str, Any]) -> dict[str, Any]:
    """One order's grids ([udc][speed][torque]), status counts and cells, as the JSON export writes them."""
    return {
        "theta_cos_rad": grid_values(m, "theta_cos"),
        "theta_sin_rad": grid_values(m, "theta_sin"),
        "valid": grid_values(m, "valid"),
        "filled": grid_values(m, "filled"),
        "injection_off": grid_values(m, "injection_off"),
        "status_counts": m.get("status_counts"),
        "cells": [
            {
                **{k: v for k, v in c.items() if k not in map_quality.CELL_FIELDS},
                "filled": cell_flag(c) == lut_codec.FLAG_FILLED,
                "fill_source": c.get("fill_source") if cell_flag(c) == lut_codec.FLAG_FILLED else None,
                "injection_off": cell_flag(c) == lut_codec.FLAG_OFF,
            }
            for c in m["cells"]
        ],
    }


def _c_nested(values: Any, leaf: Callable[[Any], str]) -> str:
    """A (nested) list as a C initialiser, each value written by `leaf`."""
    if isinstance(values, list) and values and isinstance(values[0], list):
        return "{" + ", ".join(_c_nested(v, leaf) for v in values) + "}"
    return "{" + ", ".join(leaf(v) for v in values) + "}"


def _c_array(values: Any) -> str:
    return _c_nested(values, _c_float)


def _c_u8_array(values: Any) -> str:
    return _c_nested(values, lambda v: f"{int(v)}u")


def _c_float(value: float) -> str:
    text = f"{float(value):.9g}"
    if not any(ch in text for ch in ".en"):
        text += ".0"  # "0f" is not a C literal; "0.0f" is
    return text + "f"


def export_c(m: dict[str, Any], interpolation: str | None = None) -> str:
    """The C header: the map's arrays and the reference interpolator (`ripplecal_lut_map<ID>_theta`); a map of
    several orders has one such block per further order (names `ripplecal_lut_map<ID>_h<order>_*`), and
    `ripplecal_lut_map<ID>_theta_orders` gives every order's theta as the drive injects them together."""
    mode = map_interpolation(m, interpolation)
    maps = order_maps(m)
    blocks = [_c_order_header(om, mode, "" if k == 0 else f"_h{om['harmonic_order']}") for k, om in enumerate(maps)]
    if len(maps) > 1:
        blocks.append(_c_orders_function(int(m["id"]), [om["harmonic_order"] for om in maps]))
    return "\n".join(blocks)


def _c_orders_function(map_id: int, orders: list[int]) -> str:
    """The drive's rule for several orders in C: each order's theta unclamped, then one factor on all of them so
    that the sum of their |theta| is at most gamma_max (plant_emulator/drive_firmware.py _scale)."""
    macro, array = f"RIPPLECAL_LUT_MAP{map_id}", f"ripplecal_lut_map{map_id}"
    prefixes = [array] + [f"{array}_h{h}" for h in orders[1:]]
    calls = "\n".join(
        f"    {p}_theta(torque_nm, speed_rpm, udc_v, with_fill, HUGE_VALF, &theta_cos_rad[{k}], &theta_sin_rad[{k}]);"
        for k, p in enumerate(prefixes)
    )
    return f"""#ifndef {macro}_ORDERS_H
#define {macro}_ORDERS_H
/* several orders: {macro}_N_ORDERS thetas, in the order of {array}_orders (the map's own first). The drive injects
 * v_inj = sum_k theta_cos_k cos(h_k phi_e) + theta_sin_k sin(h_k phi_e) as one voltage-angle rotation, every theta
 * scaled by one factor so that sum_k |theta_k| <= gamma_max_rad (HUGE_VALF: no clamp). */
#define {macro}_N_ORDERS {len(orders)}u
static const uint8_t {array}_orders[{len(orders)}] = {{{", ".join(f"{h}u" for h in orders)}}};

static inline void {array}_theta_orders(float torque_nm, float speed_rpm, float udc_v, int with_fill,
                                        float gamma_max_rad, float theta_cos_rad[{len(orders)}],
                                        float theta_sin_rad[{len(orders)}])
{{
    float total = 0.0f;
    unsigned k;
{calls}
    for (k = 0u; k < {macro}_N_ORDERS; k++) {{
        total += hypotf(theta_cos_rad[k], theta_sin_rad[k]);
    }}
    if (total > gamma_max_rad && total > 0.0f) {{
        for (k = 0u; k < {macro}_N_ORDERS; k++) {{
            theta_cos_rad[k] *= gamma_max_rad / total;
            theta_sin_rad[k] *= gamma_max_rad / total;
        }}
    }}
}}
#endif /* {macro}_ORDERS_H */
"""


def _c_order_header(m: dict[str, Any], mode: str, suffix: str = "") -> str:
    """One order's guarded block: its arrays and its own interpolator, every name with the map id and `suffix`."""
    nt, nn, nu = (len(m["axes"][k]) for k in ("torque_nm", "speed_rpm", "udc_v"))
    # every name carries the map id (and a further order's, its order), so several go into one translation unit
    macro, array = f"RIPPLECAL_LUT_MAP{int(m['id'])}{suffix.upper()}", f"ripplecal_lut_map{int(m['id'])}{suffix}"
    guard = f"{macro}_H"
    # a version 7 image's cells as the drive holds them (its derived cells interpolated along their rows)
    held = lut_codec.decode(order_image(m, interpolation=mode)) if cell_format(m) == lut_codec.SPARSE else None

    def flag_array(key: str, flag: int) -> Any:
        return grid_values(m, key) if held is None else (held.flags == flag).astype(int).tolist()

    version = re.sub(r"[^0-9A-Za-z.+-]", "", __version__)
    lines = [
        f"/* ripplecal LUT for harmonic injection: map {m['id']}, method {m['method']}.",
        f" * Bench: {m['bench_identity']}; created {m['created_at']}; software version {version}.",
        " * v_inj = theta_cos*cos(h*phi_e) + theta_sin*sin(h*phi_e)  [rad], applied as a voltage-angle",
        " * rotation (|u_dq*| = |u_dq|); gamma = |theta|, delta = -atan2(theta_sin, theta_cos).",
        " * Index order [udc][speed][torque]; each axis its own strictly increasing breakpoints (interpolate",
        " * by position, clamp at the ends). valid == 1: an ok result; filled == 1: a fill (not a result at",
        " * its target: inject there only if the fill is wanted); injection_off == 1: inject NOTHING (theta 0)",
        " * wherever a corner of non-zero weight has it (its theta is kept for the record; LUT image flag 3);",
        " * all three 0: theta 0, no injection.",
        f" * Interpolation ({macro}_INTERPOLATION): {interpolation_text(mode)}.",
        f" * Cells: {_counts_text(m)}; {_filled_text(m)}; {_off_text(m)}.",
        f" * Names carry the map id ({macro}_*, {array}_*).",
        f" * {_quality_text(m)}.",
        f" * {_validation_text(m)}.",
        " */",
        f"#ifndef {guard}",
        f"#define {guard}",
        "",
        "#include <float.h>",
        "#include <math.h>",
        "#include <stdint.h>",
        "",
        f"#define {macro}_ID {int(m['id'])}u",
        f'#define {macro}_SOFTWARE_VERSION "{version}"',
        f"#define {macro}_HARMONIC_ORDER {int(m['harmonic_order'])}u",
        f"#define {macro}_N_TORQUE {nt}u",
        f"#define {macro}_N_SPEED {nn}u",
        f"#define {macro}_N_UDC {nu}u",
        "/* interpolation modes (the LUT image's header byte) and the one this LUT is meant for */",
        f"#define {macro}_INTERPOLATION_CARTESIAN {lut_codec.INTERPOLATIONS.index('cartesian')}u",
        f"#define {macro}_INTERPOLATION_POLAR {lut_codec.INTERPOLATIONS.index('polar')}u",
        f"#define {macro}_INTERPOLATION_CUBIC {lut_codec.INTERPOLATIONS.index('cubic')}u",
        f"#define {macro}_INTERPOLATION {macro}_INTERPOLATION_{mode.upper()}",
        f"#define {macro}_FILLED_CELLS {sum(1 for c in m['cells'] if cell_flag(c) == lut_codec.FLAG_FILLED)}u",
        f"#define {macro}_INJECTION_OFF_CELLS {_off_cells(m)}u",
        "",
        f"/* torque axis, Nm */\nstatic const float {array}_torque_nm[{nt}] = {_c_array(m['axes']['torque_nm'])};",
        f"/* speed axis, rpm (mechanical) */\nstatic const float {array}_speed_rpm[{nn}] = {_c_array(m['axes']['speed_rpm'])};",
        f"/* DC-link voltage axis, V */\nstatic const float {array}_udc_v[{nu}] = {_c_array(m['axes']['udc_v'])};",
        "",
        *_c_theta_arrays(m, array, macro, (nu, nn, nt), held),
        f"/* 1 where the cell holds an identified value (ok) */\n"
        f"static const uint8_t {array}_valid[{nu}][{nn}][{nt}] = {_c_u8_array(flag_array('valid', lut_codec.FLAG_OK))};",
        f"/* 1 where the cell holds a fill (not ok; service/maps/fill.py) */\n"
        f"static const uint8_t {array}_filled[{nu}][{nn}][{nt}] = "
        f"{_c_u8_array(flag_array('filled', lut_codec.FLAG_FILLED))};",
        f"/* 1 where injection is off: theta 0 in every interval with this cell as a corner of non-zero weight */\n"
        f"static const uint8_t {array}_injection_off[{nu}][{nn}][{nt}] = "
        f"{_c_u8_array(flag_array('injection_off', lut_codec.FLAG_OFF))};",
        "",
        _c_interpolator(array, macro),
        "",
        f"#endif /* {guard} */",
        "",
    ]
    return "\n".join(lines)


# The reference interpolator in the header: the drive's rule (drivers/lut_image.py Lut.theta, then the clamp
# to gamma_max of plant_emulator/drive_firmware.py effective_theta), in C99 on the header's arrays. `@A`
# stands for the map's array prefix, `@M` for its macro prefix (str.format would trip over C's braces).
_C_INTERPOLATOR = r"""/* Reference interpolator: the drive's rule (docs/interfaces.md "LUT image"; drivers/lut_image.py
 * Lut.theta), to use as is. C99, no allocation, no state; from <math.h> only cosf, sinf, atan2f,
 * hypotf (polar) and isfinite (link with -lm where libm is separate).
 *
 * @A_theta(torque_nm, speed_rpm, udc_v, with_fill, gamma_max_rad, &theta_cos_rad, &theta_sin_rad):
 * theta (rad) at an operating point, interpolated by @M_INTERPOLATION:
 * - per axis x clamped to the axis ends (not finite: the first breakpoint); weights by position in
 *   x_j <= x < x_j+1; the corners of the enclosing cell with weight > 0 take part;
 * - any such corner with injection_off == 1: theta = (0, 0) exactly;
 * - entries: valid cells, and filled cells when with_fill != 0 (as the LUT download's `fill`, default
 *   on, puts them into the drive's image); other cells count as theta 0;
 * - cartesian: theta multilinear; polar: gamma multilinear, delta averaged over the corners with an
 *   entry and gamma > 0, each unwrapped to within +-pi of the one with the largest weight (the first in
 *   [udc][speed][torque] order on a tie), weights renormalised over them; cubic: the cubic Hermite of
 *   each row's theta along speed, then of those rows' values across torque, each corner's slope the
 *   three-point derivative from its neighbours where they and it are whole (else the interval's secant; a
 *   corner not whole: linear), then linear across U_dc;
 * - then, as the drive: |theta| clamped to gamma_max_rad (0x2000:5, 0 .. pi; 0 gives theta 0); pass
 *   HUGE_VALF for no clamp. */

/* the corners (1 or 2) of weight > 0 around x on a strictly increasing axis, clamped at its ends */
static inline unsigned @A_axis_corners(const float *axis, unsigned n, float x, unsigned index[2],
                                       float weight[2])
{
    unsigned j = 0u;
    float f;
    if (n == 1u || !isfinite(x) || x <= axis[0]) {
        index[0] = 0u;
        weight[0] = 1.0f;
        return 1u;
    }
    if (x >= axis[n - 1u]) {
        index[0] = n - 1u;
        weight[0] = 1.0f;
        return 1u;
    }
    while (axis[j + 1u] <= x) {
        j++;
    }
    index[0] = j;
    weight[0] = 1.0f;
    if (x == axis[j]) {
        return 1u; /* on the breakpoint: the next one weighs 0 */
    }
    f = (x - axis[j]) / (axis[j + 1u] - axis[j]);
    if (f >= 1.0f) {
        f = 1.0f - 0.5f * FLT_EPSILON; /* x < x_j+1: its lower corner keeps a weight > 0 in float too */
    }
    index[1] = j + 1u;
    weight[0] = 1.0f - f;
    weight[1] = f;
    return 2u;
}

/* a cell the drive injects at: valid, or filled when the fill is in */
static inline int @A_entry(unsigned u, unsigned n, unsigned t, int with_fill)
{
    return @A_valid[u][n][t] || (with_fill && @A_filled[u][n][t]);
}

/* the cubic Hermite on an axis between x[j] and x[j+1] at weight f of x[j+1]: values v0, v1 at the corners, vl at
 * x[j-1] (have_l) and vr at x[j+2] (have_r) for the slopes (the three-point derivative; else the secant) */
static inline float @A_hermite(const float *x, unsigned j, float f, float v0, float v1, int have_l, float vl,
                               int have_r, float vr)
{
    const float h = x[j + 1u] - x[j], d = (v1 - v0) / h;
    float m0 = d, m1 = d;
    if (have_l) {
        const float hl = x[j] - x[j - 1u];
        m0 = (h * (v0 - vl) / hl + hl * d) / (hl + h);
    }
    if (have_r) {
        const float hr = x[j + 2u] - x[j + 1u];
        m1 = (hr * d + h * (vr - v1) / hr) / (h + hr);
    }
    return (1.0f + 2.0f * f) * (1.0f - f) * (1.0f - f) * v0 + f * (1.0f - f) * (1.0f - f) * h * m0 +
           f * f * (3.0f - 2.0f * f) * v1 + f * f * (f - 1.0f) * h * m1;
}

/* cubic along speed in the row (u, t) at the nn (1 or 2) speed corners in[] of weights wn[], as Lut.theta's rows;
 * returns 1 where the row is whole there (every speed corner of weight > 0 an entry) */
static inline int @A_cubic_row(unsigned u, unsigned t, const unsigned in[2], const float wn[2], unsigned nn,
                               int with_fill, float *theta_cos_rad, float *theta_sin_rad)
{
    const unsigned j = in[0];
    const int e0 = @A_entry(u, j, t, with_fill);
    const float c0 = e0 ? @M_THETA_COS(u, j, t) : 0.0f, s0 = e0 ? @M_THETA_SIN(u, j, t) : 0.0f;
    float c1, s1;
    int e1, have_l, have_r;
    if (nn == 1u) {
        *theta_cos_rad = c0;
        *theta_sin_rad = s0;
        return e0;
    }
    e1 = @A_entry(u, j + 1u, t, with_fill);
    c1 = e1 ? @M_THETA_COS(u, j + 1u, t) : 0.0f;
    s1 = e1 ? @M_THETA_SIN(u, j + 1u, t) : 0.0f;
    if (!e0 || !e1) { /* a corner without an entry: linear */
        *theta_cos_rad = wn[0] * c0 + wn[1] * c1;
        *theta_sin_rad = wn[0] * s0 + wn[1] * s1;
        return 0;
    }
    have_l = j > 0u && @A_entry(u, j - 1u, t, with_fill);
    have_r = j + 2u < @M_N_SPEED && @A_entry(u, j + 2u, t, with_fill);
    *theta_cos_rad = @A_hermite(@A_speed_rpm, j, wn[1], c0, c1, have_l, have_l ? @M_THETA_COS(u, j - 1u, t) : 0.0f,
                                have_r, have_r ? @M_THETA_COS(u, j + 2u, t) : 0.0f);
    *theta_sin_rad = @A_hermite(@A_speed_rpm, j, wn[1], s0, s1, have_l, have_l ? @M_THETA_SIN(u, j - 1u, t) : 0.0f,
                                have_r, have_r ? @M_THETA_SIN(u, j + 2u, t) : 0.0f);
    return 1;
}

/* cubic across torque at U_dc index u: the rows' theta at the speed (in[], wn[], nn) between the torque corners
 * it[] (weights wt[], nt of them), the Hermite where both corner rows are whole, each slope from the rows beside
 * them where those are whole; else linear, as Lut.theta */
static inline void @A_cubic_column(unsigned u, const unsigned it[2], const float wt[2], unsigned nt,
                                   const unsigned in[2], const float wn[2], unsigned nn, int with_fill,
                                   float *theta_cos_rad, float *theta_sin_rad)
{
    const unsigned j = it[0];
    float c0, s0, c1 = 0.0f, s1 = 0.0f, cl = 0.0f, sl = 0.0f, cr = 0.0f, sr = 0.0f;
    int w0, w1, have_l = 0, have_r = 0;
    w0 = @A_cubic_row(u, j, in, wn, nn, with_fill, &c0, &s0);
    if (nt == 1u) {
        *theta_cos_rad = c0;
        *theta_sin_rad = s0;
        return;
    }
    w1 = @A_cubic_row(u, j + 1u, in, wn, nn, with_fill, &c1, &s1);
    if (!w0 || !w1) {
        *theta_cos_rad = wt[0] * c0 + wt[1] * c1;
        *theta_sin_rad = wt[0] * s0 + wt[1] * s1;
        return;
    }
    if (j > 0u) {
        have_l = @A_cubic_row(u, j - 1u, in, wn, nn, with_fill, &cl, &sl);
    }
    if (j + 2u < @M_N_TORQUE) {
        have_r = @A_cubic_row(u, j + 2u, in, wn, nn, with_fill, &cr, &sr);
    }
    *theta_cos_rad = @A_hermite(@A_torque_nm, j, wt[1], c0, c1, have_l, cl, have_r, cr);
    *theta_sin_rad = @A_hermite(@A_torque_nm, j, wt[1], s0, s1, have_l, sl, have_r, sr);
}

/* polar over the corners: gamma multilinear, delta along the shortest arc around the reference */
static inline void @A_polar(unsigned corner[8][3], const float weight[8], unsigned n_corners,
                            int with_fill, float *theta_cos_rad, float *theta_sin_rad)
{
    const float pi = 3.14159265358979f;
    float gamma_c[8], delta_c[8], gamma = 0.0f, w_sum = 0.0f, delta_sum = 0.0f, delta_ref = 0.0f, w_ref = 0.0f;
    int phase[8], have_ref = 0;
    unsigned k;
    for (k = 0u; k < n_corners; k++) {
        const unsigned u = corner[k][0], n = corner[k][1], t = corner[k][2];
        const float cos_c = @M_THETA_COS(u, n, t), sin_c = @M_THETA_SIN(u, n, t);
        gamma_c[k] = hypotf(cos_c, sin_c);
        delta_c[k] = -atan2f(sin_c, cos_c);
        /* a zero theta has no phase */
        phase[k] = @A_entry(u, n, t, with_fill) && gamma_c[k] > 0.0f;
        if (phase[k] && (!have_ref || weight[k] > w_ref)) {
            have_ref = 1; /* the first of the largest weight */
            w_ref = weight[k];
            delta_ref = delta_c[k];
        }
    }
    if (!have_ref) {
        *theta_cos_rad = 0.0f;
        *theta_sin_rad = 0.0f;
        return;
    }
    for (k = 0u; k < n_corners; k++) {
        float arc;
        if (!phase[k]) {
            continue;
        }
        /* (delta_c - delta_ref + pi) mod 2 pi, both deltas in [-pi, pi] */
        arc = delta_c[k] - delta_ref + pi;
        if (arc < 0.0f) {
            arc += 2.0f * pi;
        } else if (arc >= 2.0f * pi) {
            arc -= 2.0f * pi;
        }
        gamma += weight[k] * gamma_c[k];
        delta_sum += weight[k] * (delta_ref + arc - pi);
        w_sum += weight[k];
    }
    *theta_cos_rad = gamma * cosf(delta_sum / w_sum);
    *theta_sin_rad = -gamma * sinf(delta_sum / w_sum);
}

static inline void @A_theta(float torque_nm, float speed_rpm, float udc_v, int with_fill,
                            float gamma_max_rad, float *theta_cos_rad, float *theta_sin_rad)
{
    unsigned it[2], in[2], iu[2], nt, nn, nu, a, b, c, k, n_corners = 0u;
    unsigned corner[8][3];
    float wt[2] = {1.0f, 0.0f}, wn[2] = {1.0f, 0.0f}, wu[2], weight[8], tc = 0.0f, ts = 0.0f, gamma;
    nt = @A_axis_corners(@A_torque_nm, @M_N_TORQUE, torque_nm, it, wt);
    nn = @A_axis_corners(@A_speed_rpm, @M_N_SPEED, speed_rpm, in, wn);
    nu = @A_axis_corners(@A_udc_v, @M_N_UDC, udc_v, iu, wu);
    *theta_cos_rad = 0.0f;
    *theta_sin_rad = 0.0f;
    /* the corners in [udc][speed][torque] index order */
    for (a = 0u; a < nu; a++) {
        for (b = 0u; b < nn; b++) {
            for (c = 0u; c < nt; c++) {
                if (@A_injection_off[iu[a]][in[b]][it[c]]) {
                    return; /* injection off: exactly no compensation */
                }
                corner[n_corners][0] = iu[a];
                corner[n_corners][1] = in[b];
                corner[n_corners][2] = it[c];
                weight[n_corners] = wu[a] * wn[b] * wt[c];
                n_corners++;
            }
        }
    }
    if (@M_INTERPOLATION == @M_INTERPOLATION_POLAR) {
        @A_polar(corner, weight, n_corners, with_fill, &tc, &ts);
    } else if (@M_INTERPOLATION == @M_INTERPOLATION_CUBIC) {
        for (a = 0u; a < nu; a++) {
            float rc, rs;
            @A_cubic_column(iu[a], it, wt, nt, in, wn, nn, with_fill, &rc, &rs);
            tc += wu[a] * rc;
            ts += wu[a] * rs;
        }
    } else {
        for (k = 0u; k < n_corners; k++) {
            const unsigned u = corner[k][0], n = corner[k][1], t = corner[k][2];
            if (@A_entry(u, n, t, with_fill)) { /* no entry: theta 0 */
                tc += weight[k] * @M_THETA_COS(u, n, t);
                ts += weight[k] * @M_THETA_SIN(u, n, t);
            }
        }
    }
    /* as the drive: |theta| clamped to gamma_max */
    gamma = hypotf(tc, ts);
    if (gamma > gamma_max_rad && gamma > 0.0f) {
        tc *= gamma_max_rad / gamma;
        ts *= gamma_max_rad / gamma;
    }
    *theta_cos_rad = tc;
    *theta_sin_rad = ts;
}"""


def _c_theta_arrays(
    m: dict[str, Any], array: str, macro: str, shape: tuple[int, int, int], held: lut_codec.Lut | None = None
) -> list[str]:
    """theta_cos and theta_sin as the map's LUT image carries them: f32 arrays, or (int16 and int11 cells) i16
    arrays and their quantum, the same integers as the drive's image (int11: within +-1023, unpacked from the
    image's 24-bit words: the header keeps one array per component for the firmware to read directly);
    <MACRO>_THETA_COS(u, n, t) reads any of them in rad."""
    nu, nn, nt = shape
    dims = f"[{nu}][{nn}][{nt}]"
    what = "(ok, filled and injection-off cells; 0 elsewhere)"
    tc, ts = grid_values(m, "theta_cos"), grid_values(m, "theta_sin")
    cells = cell_format(m)
    if held is not None:  # version 7: every cell as the drive holds it, f32 (the header is the firmware's full grid)
        stored = int(np.count_nonzero(held.stored)) if held.stored is not None else held.flags.size
        what = (
            f"(LUT image version 7 expanded: {stored} of {held.flags.size} cells stored, the others as the drive "
            "derives them along their row; 0 where there is no entry)"
        )
        tc, ts = held.theta_cos.tolist(), held.theta_sin.tolist()
    if cells not in lut_codec.FULL_SCALE or held is not None:
        return [
            f"/* theta_cos, rad {what} */\nstatic const float {array}_theta_cos_rad{dims} = {_c_array(tc)};",
            f"/* theta_sin, rad {what} */\nstatic const float {array}_theta_sin_rad{dims} = {_c_array(ts)};",
            f"#define {macro}_THETA_COS(u, n, t) ({array}_theta_cos_rad[u][n][t])",
            f"#define {macro}_THETA_SIN(u, n, t) ({array}_theta_sin_rad[u][n][t])",
        ]
    quantum = _theta_quantum(m)

    def ints(values: list[list[list[float]]]) -> str:
        return _c_nested(lut_codec.quantized(values, quantum, cells).tolist(), lambda v: str(int(v)))

    version = lut_codec.format_version_of([], cells)
    return [
        f"/* theta quantum, rad: theta = q * quantum (LUT image version {version}, {cells} cells) */\n"
        f"#define {macro}_THETA_QUANTUM_RAD {float(np.float32(quantum))!r}f",
        f"/* theta_cos / quantum {what} */\nstatic const int16_t {array}_theta_cos_q{dims} = {ints(tc)};",
        f"/* theta_sin / quantum {what} */\nstatic const int16_t {array}_theta_sin_q{dims} = {ints(ts)};",
        f"#define {macro}_THETA_COS(u, n, t) ((float){array}_theta_cos_q[u][n][t] * {macro}_THETA_QUANTUM_RAD)",
        f"#define {macro}_THETA_SIN(u, n, t) ((float){array}_theta_sin_q[u][n][t] * {macro}_THETA_QUANTUM_RAD)",
    ]


def _c_interpolator(array: str, macro: str) -> str:
    return _C_INTERPOLATOR.replace("@A", array).replace("@M", macro)


def export_cdfx(m: dict[str, Any], interpolation: str | None = None) -> str:
    """ASAM CDF 2.0 (service/maps/cdfx.py), from the values every other export writes."""
    from service.maps import cdfx  # it imports this module's cell values: imported here, not at the top

    return cdfx.export_cdfx(m, interpolation)


def shortest_number(x: float) -> str:
    """The shortest text that reads back as the same double (distinct breakpoints stay distinct)."""
    text = repr(float(x))
    return text[:-2] if text.endswith(".0") else text


def export_dcm(m: dict[str, Any], interpolation: str | None = None) -> str:
    """DCM 2.0 (calibration data exchange format read by INCA / CANape): one KENNFELD per U_dc and
    theta component, VALID, FILLED and INJECTION_OFF, x = torque (Nm), y = speed (rpm), each with its axis points
    (ST/X, ST/Y: the map's own breakpoints, non-uniform as they are)."""
    mode = map_interpolation(m, interpolation)
    axes = m["axes"]
    nt, nn = len(axes["torque_nm"]), len(axes["speed_rpm"])
    out = [
        f"* ripplecal LUT, map {m['id']}, harmonic order h = {m['harmonic_order']}, method {m['method']}",
        f"* software version {__version__}, bench {m['bench_identity']}, created {m['created_at']}",
        f"* cells: {_counts_text(m)}; VALID = 1 only where the result met its target (ok); "
        f"FILLED = 1 where a cell not ok carries a fill (THETA holds it); {_filled_text(m)}",
        f"* INJECTION_OFF = 1: no injection in any interval with this cell as a corner of non-zero weight; {_off_text(m)}",
        f"* LUT interpolation: {interpolation_text(mode)}",
        f"* {_quality_text(m)}",
        f"* {_validation_text(m)}",
        "KONSERVIERUNG_FORMAT 2.0",
        "",
    ]
    kennfelder = (
        ("THETA_COS", "theta_cos"),
        ("THETA_SIN", "theta_sin"),
        ("VALID", "valid"),
        ("FILLED", "filled"),
        ("INJECTION_OFF", "injection_off"),
    )
    if len(map_orders(m)) > 1:
        out.insert(
            -2,
            f"* several orders: {', '.join(str(h) for h in map_orders(m))}, each its own KENNFELDER (RIPPLECAL_H<h>_*)",
        )
    for om in order_maps(m):
        out += _dcm_kennfelder(om, kennfelder, nt, nn)
    return "\n".join(out)


def _dcm_kennfelder(m: dict[str, Any], kennfelder: tuple[tuple[str, str], ...], nt: int, nn: int) -> list[str]:
    """One order's KENNFELDER (its order in their names)."""
    axes, out = m["axes"], []
    planes = {key: grid_values(m, key) for _, key in kennfelder}
    for name, key in kennfelder:
        for k, udc in enumerate(axes["udc_v"]):
            plane = planes[key][k]
            out += [
                f"KENNFELD RIPPLECAL_H{m['harmonic_order']}_{name}_U{udc:g}V".replace(".", "P") + f" {nt} {nn}",
                f'   LANGNAME "{name.lower()} at U_dc = {udc:g} V"',
                '   EINHEIT_X "Nm"',
                '   EINHEIT_Y "rpm"',
                f'   EINHEIT_W "{"rad" if key.startswith("theta") else "-"}"',
                "   ST/X   " + "   ".join(shortest_number(t) for t in axes["torque_nm"]),
            ]
            for j, speed in enumerate(axes["speed_rpm"]):
                values = plane[j] if key.startswith("theta") else [int(v) for v in plane[j]]
                out += [
                    f"   ST/Y   {shortest_number(speed)}",
                    "   WERT   " + "   ".join(f"{v:.9g}" if key.startswith("theta") else str(v) for v in values),
                ]
            out += ["END", ""]
    return out


CELL_FORMATS = lut_codec.CELL_FORMATS
SPARSE = lut_codec.SPARSE  # the cell format of a version 7 image (per-row speed breakpoints)


def cell_count(axes: dict[str, list[float]]) -> int:
    """Cells of a full grid with these axes."""
    return math.prod(len(axes[a]) for a in lut_codec.AXES)


def image_bytes(axes: dict[str, list[float]], cells: str = "float32", stored: int | None = None) -> int:
    """Bytes of the LUT image (firmware memory) of a map with these axes: header, each axis' breakpoints (f32),
    theta_cos and theta_sin (f32, or integers after one f32 quantum with cells "int16" or "int11") and the flag per
    cell (CELL_BYTES a cell in all), CRC (drivers/lut_image.py layout). "int11-sparse": one bit a cell and
    CELL_BYTES per stored cell (`stored` of them; None: all)."""
    quantum = 4 if cells in lut_codec.FULL_SCALE else 0
    n = cell_count(axes)
    per_cell = lut_codec.CELL_BYTES[cells] * n
    if cells == lut_codec.SPARSE:
        per_cell = (n + 7) // 8 + lut_codec.CELL_BYTES[cells] * (n if stored is None else stored)
    return (
        lut_codec.HEADER.size
        + 4 * sum(len(axes[a]) for a in lut_codec.AXES)
        + quantum
        + per_cell
        + lut_codec.TRAILER.size
    )


# a cell a version 7 image leaves out is reproduced by its row's interpolation within this under its |theta|: the
# refinement's 30 dB and the placement's margin (service/maps/placement.py PLACE_MARGIN_DB), unless the map's
# provenance names another (`lut_sparse_db`)
SPARSE_BAR_DB = 36.0
# with a budget (`lut_max_bytes`) the image is filled up to it: the bar rises to at most this (identification itself
# holds theta* to about this, so a higher bar buys nothing measurable)
SPARSE_BAR_MAX_DB = 60.0


def row_stored(
    speed_rpm: list[float],
    thetas: list[complex | None],
    bar_db: float,
    interpolation: str,
    flags: list[int] | None = None,
) -> list[bool]:
    """Which cells of one row along speed a version 7 image stores (None: a cell without an entry, always stored):
    greedy from the row's start, each stored cell followed by the farthest cell whose interpolation from it
    (drivers.lut_image.between, the drive's) reproduces every cell between them within bar_db under that cell's
    |theta|, 20 log10 |theta| / |error| (the LUT-mode suppression there, service/maps/placement.py predicted_db),
    and all of whose cells carry the same flag (`flags`, default all alike: a derived cell takes its ends' flag).
    The first and last cells are always stored."""
    n = len(thetas)
    flag = flags or [lut_codec.FLAG_OK] * n
    keep = [True] * n
    a = 0
    while a < n - 1:
        b = a + 1
        while b + 1 < n and thetas[a] is not None and thetas[b + 1] is not None:
            ta, tb = cast(complex, thetas[a]), cast(complex, thetas[b + 1])
            ok = True
            if flag[b + 1] != flag[a]:
                break
            for k in range(a + 1, b + 1):
                tk = thetas[k]
                if tk is None or flag[k] != flag[a]:
                    ok = False
                    break
                error = abs(lut_codec.between(ta, tb, speed_rpm[a], speed_rpm[b + 1], speed_rpm[k], interpolation) - tk)
                if error > 0.0 and (abs(tk) == 0.0 or 20.0 * math.log10(abs(tk) / error) < bar_db):
                    ok = False
                    break
            if not ok:
                break
            b += 1
        for k in range(a + 1, b):
            keep[k] = False
        a = b
    return keep


def stored_mask(
    speed_rpm: list[float], theta_cos: Any, theta_sin: Any, flags: Any, bar_db: float, interpolation: str
) -> np.ndarray:
    """The cells a version 7 image stores, bool [udc][speed][torque]: `row_stored` per row; an off cell or one
    without an entry is stored and ends the rows' interpolation there."""
    tc, ts, f = (np.asarray(x, dtype=float) for x in (theta_cos, theta_sin, flags))
    nu, nn, nt = f.shape
    entry = (f == lut_codec.FLAG_OK) | (f == lut_codec.FLAG_FILLED)
    speeds = [float(v) for v in speed_rpm]
    keep = np.ones(f.shape, dtype=bool)
    for iu in range(nu):
        for it in range(nt):
            row = [complex(tc[iu, j, it], ts[iu, j, it]) if entry[iu, j, it] else None for j in range(nn)]
            keep[iu, :, it] = row_stored(speeds, row, bar_db, interpolation, [int(x) for x in f[iu, :, it]])
    return keep


def sparse_bar_db(m: dict[str, Any]) -> float:
    """The bar a map's version 7 image leaves cells out at (`SPARSE_BAR_DB` unless its provenance names one)."""
    return float((m.get("provenance") or {}).get("lut_sparse_db", SPARSE_BAR_DB))


def lut_image(m: dict[str, Any], fill: bool = True, interpolation: str | None = None) -> bytes:
    """The binary image the drive takes on 0x2001:1: a map of one order's (`order_image`), or for a map of several
    orders the version 8 image of one such image per order, its own first (drivers/lut_image.py encode_orders)."""
    maps = order_maps(m)
    mode = map_interpolation(m, interpolation)
    if len(maps) == 1:
        return order_image(m, fill, mode)
    return lut_codec.encode_orders([order_image(om, fill, mode) for om in maps])


def order_image(m: dict[str, Any], fill: bool = True, interpolation: str | None = None) -> bytes:
    """The binary image the drive takes on 0x2001:1, carrying the map's id (docs/interfaces.md, "LUT
    image"; encoded by drivers.lut_image, the one definition the drive firmware decodes with). fill:
    filled cells go in as flag 2 (the drive injects their fill), else as flag 0 (no entry); cells with
    injection off go in as flag 3 (format_version 4; without one the image is version 3; a map built for int16,
    int11 or int11-sparse cells, `cell_format`, is version 5, 6 or 7: version 7 stores the cells `stored_mask`
    keeps at `sparse_bar_db`, judged on the values the image carries; with a budget, the map's `lut_max_bytes`, the
    highest bar whose image fits it);
    interpolation: the mode in the header (None: the map's own, `map_interpolation`). Raises
    ValueError if the map cannot become an image (too many cells, an axis not strictly increasing)."""
    axes = m["axes"]
    cells = cell_format(m)
    mode = map_interpolation(m, interpolation)
    tc, ts, flags = (grid_values(m, key, fill) for key in ("theta_cos", "theta_sin", "flag"))
    stored = None
    if cells == lut_codec.SPARSE:
        quantum = lut_codec.theta_quantum(np.asarray(tc), np.asarray(ts), cells)
        carried_cos, carried_sin = (lut_codec.quantized(v, quantum, cells) * quantum for v in (tc, ts))
        budget = (m.get("provenance") or {}).get("lut_max_bytes")
        max_bytes = None if budget is None else int(budget)

        def stored_at(bar_db: float) -> np.ndarray:
            return stored_mask(axes["speed_rpm"], carried_cos, carried_sin, flags, bar_db, mode)

        if max_bytes is None:
            stored = stored_at(sparse_bar_db(m))
        elif image_bytes(axes, cells) > max_bytes:  # (within it: every cell stored, encode's default)
            # the budget is firmware memory, spent: the highest whole-dB bar up to SPARSE_BAR_MAX_DB that fits (or
            # every cell), below the map's bar where even that does not (bisection: a higher bar stores more)
            low, high = 0, int(SPARSE_BAR_MAX_DB)
            stored = stored_at(low)
            while low < high:
                mid = (low + high + 1) // 2
                trial = stored_at(float(mid))
                if image_bytes(axes, cells, int(trial.sum())) <= max_bytes:
                    low, stored = mid, trial
                else:
                    high = mid - 1
    return lut_codec.encode(
        m["harmonic_order"],
        *cast(tuple[Any, Any, Any], tuple(axes[key] for key in lut_codec.AXES)),  # torque, speed, udc
        tc,
        ts,
        flags,
        map_id=m["id"],
        interpolation=mode,
        cell_format=cells,
        stored=stored,
    )


def _speeds_spanning(breakpoints: list[float], lo: float, hi: float) -> list[float]:
    """The speeds at which a question about the drive's LUT over [lo, hi] rpm is settled: both ends, each breakpoint
    between them and a quarter, half and three quarters of the way between each two of those (inside an interval
    every speed has the same corners of weight > 0, and the theta is an interpolation of them: linear, or in "cubic"
    a cubic along speed, which its two ends and three inner points settle)."""
    edges = sorted({lo, hi, *(b for b in breakpoints if lo < b < hi)})
    return edges + [a + k * (b - a) / 4.0 for a, b in zip(edges, edges[1:]) for k in (1, 2, 3)]


def injection_unchanged(
    before: dict[str, Any], after: dict[str, Any], fill: bool = True, interpolation: str | None = None
) -> Callable[[Mapping[str, Any], bool], bool]:
    """same(point, along_speed): True where the drive injects the same theta under both maps' LUT images (built as
    `lut_image(m, fill, interpolation)`, interpolated by Lut.theta, the drive's one definition) at the operating
    point, or (along_speed: a run-up) at every speed at its torque and U_dc: at each breakpoint of both speed axes
    and between them (`_speeds_spanning`). The same means within
    rounding: two quanta of integer cells (an inserted cell may change a map's quantum), else 1e-9 rad."""
    lut_a = lut_codec.decode(lut_image(before, fill, interpolation))
    lut_b = lut_codec.decode(lut_image(after, fill, interpolation))
    tolerance_rad = 1e-9 + 2.0 * max(_theta_quantum(before), _theta_quantum(after))
    breakpoints = sorted({float(v) for v in (*lut_a.speed_rpm, *lut_b.speed_rpm)})
    along = _speeds_spanning(breakpoints, breakpoints[0], breakpoints[-1])

    def same(point: Mapping[str, Any], along_speed: bool = False) -> bool:
        t, u = float(point["torque_nm"]), float(point["udc_v"])
        for n in along if along_speed else [float(point["speed_rpm"])]:
            (ca, sa), (cb, sb) = lut_a.theta(t, n, u), lut_b.theta(t, n, u)
            if abs(ca - cb) > tolerance_rad or abs(sa - sb) > tolerance_rad:
                return False
        return True

    return same


def injects_nothing(
    m: dict[str, Any], fill: bool = True, interpolation: str | None = None
) -> Callable[[Mapping[str, Any], float], bool]:
    """nothing(point, half_width_rpm): True where the drive injects exactly nothing under the map's LUT image (built
    as `lut_image(m, fill, interpolation)`, interpolated by Lut.theta, the drive's one definition: a corner of weight
    > 0 turned off, flag 3, gives (0, 0)) at the operating point, or at every speed within half_width_rpm of it (a
    run-up bin; _speeds_spanning)."""
    lut = lut_codec.decode(lut_image(m, fill, interpolation))
    breakpoints = sorted(float(v) for v in lut.speed_rpm)

    def nothing(point: Mapping[str, Any], half_width_rpm: float = 0.0) -> bool:
        t, n, u = float(point["torque_nm"]), float(point["speed_rpm"]), float(point["udc_v"])
        speeds = _speeds_spanning(breakpoints, n - half_width_rpm, n + half_width_rpm)
        return all(lut.theta(t, s, u) == (0.0, 0.0) for s in speeds)

    return nothing


def _theta_quantum(m: dict[str, Any]) -> float:
    """The rad a unit of the map's integer cells stands for in its LUT image; 0 for float32 cells."""
    cells = cell_format(m)
    if cells not in lut_codec.FULL_SCALE:
        return 0.0
    return lut_codec.theta_quantum(
        np.asarray(grid_values(m, "theta_cos")), np.asarray(grid_values(m, "theta_sin")), cells
    )


# -- what the layers above see of a map's LUT image (service/runs/lut_download.py: the download rules and
# the receipt), so that they never import the wire codec (drivers/lut_image.py) themselves
LUT_FORMAT_VERSION = lut_codec.FORMAT_VERSION  # what lut_image writes for a map without injection-off cells
# the drive's mode when neither a download nor the map names one (map_interpolation)
DEFAULT_INTERPOLATION = lut_codec.DEFAULT_INTERPOLATION
crc_hex = lut_codec.crc_hex  # a CRC as the service shows it everywhere: 0x and 8 hex digits


@dataclass(frozen=True)
class LutEntries:
    """What a map's LUT image holds under a fill choice: the cells by flag and the header's mode."""

    cells: int
    ok: int  # flag 1: a result at its target
    filled: int  # flag 2: a fill (0 without fill)
    fills_left_out: int  # cells that carry a fill but go in as holes (only without fill)
    interpolation: str  # the header's mode
    injection_off: int = 0  # flag 3: chosen, so never a hole
    format_version: int = LUT_FORMAT_VERSION  # the image's (4 with an off cell)
    orders: tuple[int, ...] = ()  # every order of the image, its own first
    further_holes: int = 0  # a map of several orders: the further orders' cells without an entry

    @property
    def holes(self) -> int:
        """Cells without an entry and not chosen off, of every order: the drive injects nothing there."""
        return self.cells - self.ok - self.filled - self.injection_off + self.further_holes


def lut_entries(m: dict[str, Any], fill: bool = True, interpolation: str | None = None) -> LutEntries:
    """The entries of the image `lut_image(m, fill, interpolation)` would carry, without building it.
    Raises ValueError for an interpolation the drive does not know (the message names the ones it does)."""
    mode = map_interpolation(m, interpolation)
    flags = [cell_flag(c, fill) for c in m["cells"]]
    left_out = 0 if fill else sum(1 for c in m["cells"] if cell_flag(c, True) == lut_codec.FLAG_FILLED)
    orders = tuple(map_orders(m))
    further = [cell_flag(c, fill) for om in order_maps(m)[1:] for c in om["cells"]]
    return LutEntries(
        orders=orders,
        further_holes=further.count(lut_codec.FLAG_NONE),
        cells=len(flags),
        ok=flags.count(lut_codec.FLAG_OK),
        filled=flags.count(lut_codec.FLAG_FILLED),
        fills_left_out=left_out,
        interpolation=mode,
        injection_off=flags.count(lut_codec.FLAG_OFF),
        format_version=(
            lut_codec.FORMAT_VERSION_ORDERS if len(orders) > 1 else lut_codec.format_version_of(flags, cell_format(m))
        ),
    )


@dataclass(frozen=True)
class ExportFormat:
    name: str
    display_name: str
    media_type: str
    extension: str
    render: Callable[..., str]  # render(map_dict, interpolation=None) -> text


# the one registry of export formats: the API's `format` parameter, the CLI's choices and the
# dashboard (GET /api/v1/export-formats) read it
EXPORT_FORMATS: dict[str, ExportFormat] = {
    f.name: f
    for f in (
        ExportFormat("csv", "CSV", "text/csv", "csv", export_csv),
        ExportFormat("json", "JSON", "application/json", "json", export_json),
        ExportFormat("c", "C header", "text/x-csrc", "h", export_c),
        ExportFormat("dcm", "DCM (INCA / CANape)", "text/plain", "dcm", export_dcm),
        ExportFormat("cdfx", "CDF 2.0 (CDFX: INCA / CANape / MATLAB)", "application/xml", "cdfx", export_cdfx),
    )
}


def export_map(m: dict[str, Any], fmt: str, interpolation: str | None = None) -> str:
    """The map (MapPublic.model_dump()) as a file of format `fmt`; `interpolation`: the LUT mode the
    export names (None: the map's own, `map_interpolation`)."""
    if fmt not in EXPORT_FORMATS:
        raise ValueError(f"format {fmt!r} is not supported; choose one of {sorted(EXPORT_FORMATS)}")
    return EXPORT_FORMATS[fmt].render(m, interpolation=interpolation)
