"""ASAM CDF 2.0 (CDFX): the calibration data exchange format INCA, CANape and MATLAB's `cdfx` read, valid against
the CDF 2.0.0 DTD (`cdf_v2.0.0.sl.dtd`, as ASAM publishes it).

One MSRSW document: SW-SYSTEM `RIPPLECAL`, one SW-INSTANCE-TREE for the map, and per harmonic order, U_dc value
and characteristic one SW-INSTANCE of category MAP (the names as the DCM export's KENNFELDER:
`RIPPLECAL_H<order>_<KIND>_U<udc>V`, a decimal point written P): THETA_COS and THETA_SIN (rad, what the LUT
carries), GAMMA and DELTA (deg, for reading: gamma = |theta|, delta = -atan2(theta_sin, theta_cos) in [0, 360)),
VALID (1 where the cell's result met its target), FILLED (1 where a cell not ok carries a fill,
service/maps/fill.py) and INJECTION_OFF (1 where the drive injects nothing around the cell: LUT flag 3).
Each MAP has two SW-AXIS-CONTs, x = torque (Nm) then y = speed (rpm), category STD_AXIS, the map's own breakpoints
(non-uniform as they are), SW-ARRAYSIZE [n_torque, n_speed], and its values as one VG per torque breakpoint
holding the values along speed (values[x][y]). Cells without an entry carry 0 (as every export).
Each instance's SW-CS-HISTORY has one CS-ENTRY whose STATE says how far it is calibrated: `measured` where every
cell of the order is ok, `preliminary` where some carry a fill, `incomplete` where a cell has no entry; its
SW-CS-FLAGS count the cells by class (CATEGORY ok, filled, not_ok, injection_off; FLAG the count), so a
calibration engineer sees per instance which cells are measured, filled or not ok (VALID and FILLED say which)."""

from __future__ import annotations

import math
from typing import Any
from xml.sax.saxutils import escape

from drivers import lut_image as lut_codec
from service import __version__
from service.maps.lut_export import (
    cell_flag,
    grid_values,
    interpolation_text,
    map_interpolation,
    order_maps,
    shortest_number,
)

DOCTYPE = (
    '<!DOCTYPE MSRSW PUBLIC "-//ASAM//DTD CALIBRATION DATA FORMAT:V2.0.0:LAI:IAI:XML:CDF200.XSD//EN" '
    '"cdf_v2.0.0.sl.dtd">'
)
KINDS = (
    ("THETA_COS", "theta_cos", "rad"),
    ("THETA_SIN", "theta_sin", "rad"),
    ("GAMMA", "gamma_deg", "deg"),
    ("DELTA", "delta_deg", "deg"),
    ("VALID", "valid", "-"),
    ("FILLED", "filled", "-"),
    ("INJECTION_OFF", "injection_off", "-"),
)


def instance_name(order: int, kind: str, udc_v: float) -> str:
    """`RIPPLECAL_H<order>_<KIND>_U<udc>V` with a decimal point written P (the DCM export's names)."""
    return f"RIPPLECAL_H{order}_{kind}_U{udc_v:g}V".replace(".", "P")


def _values(m: dict[str, Any], key: str) -> list[list[list[float]]]:
    """[udc][speed][torque] values of a characteristic; gamma and delta (deg) from the theta the cells carry."""
    if key not in ("gamma_deg", "delta_deg"):
        return grid_values(m, key)
    tc, ts = grid_values(m, "theta_cos"), grid_values(m, "theta_sin")
    out = []
    for plane_c, plane_s in zip(tc, ts):
        rows = []
        for row_c, row_s in zip(plane_c, plane_s):
            if key == "gamma_deg":
                rows.append([math.degrees(math.hypot(c, s)) for c, s in zip(row_c, row_s)])
            else:
                rows.append(
                    [math.degrees(-math.atan2(s, c)) % 360.0 if (c or s) else 0.0 for c, s in zip(row_c, row_s)]
                )
        out.append(rows)
    return out


def _state(counts: dict[str, int]) -> str:
    if counts["none"]:
        return "incomplete"
    return "preliminary" if counts["filled"] else "measured"


def export_cdfx(m: dict[str, Any], interpolation: str | None = None) -> str:
    """The map (MapView.model_dump()) as a CDF 2.0 document, from the cell values and LUT flags every other export
    writes (service/maps/lut_export.py grid_values, cell_flag): CDFX says what they and the LUT image say."""
    maps = order_maps(m)
    mode_text = interpolation_text(map_interpolation(m, interpolation))
    axes = m["axes"]
    torque, speed = axes["torque_nm"], axes["speed_rpm"]
    date = str(m.get("created_at") or "")[:10]
    out = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        DOCTYPE,
        f'<MSRSW CREATOR="ripplecal" CREATOR-VERSION="{escape(__version__)}">',
        f"  <SHORT-NAME>RIPPLECAL_MAP{int(m['id'])}</SHORT-NAME>",
        "  <CATEGORY>CDF20</CATEGORY>",
        "  <SW-SYSTEMS>",
        "    <SW-SYSTEM>",
        "      <SHORT-NAME>RIPPLECAL</SHORT-NAME>",
        "      <SW-INSTANCE-SPEC>",
        "        <SW-INSTANCE-TREE>",
        f"          <SHORT-NAME>MAP{int(m['id'])}</SHORT-NAME>",
        f"          <LONG-NAME>{escape(_long_name(m, maps, mode_text))}</LONG-NAME>",
        "          <CATEGORY>NO_VCD</CATEGORY>",
    ]
    for om in maps:
        flags = [cell_flag(c) for c in om["cells"]]
        counts = {
            "ok": flags.count(lut_codec.FLAG_OK),
            "filled": flags.count(lut_codec.FLAG_FILLED),
            "injection_off": flags.count(lut_codec.FLAG_OFF),
            "none": flags.count(lut_codec.FLAG_NONE),
        }
        for kind, key, unit in KINDS:
            values = _values(om, key)
            for k, udc in enumerate(axes["udc_v"]):
                out += _instance(om["harmonic_order"], kind, unit, udc, torque, speed, values[k], counts, date)
    out += [
        "        </SW-INSTANCE-TREE>",
        "      </SW-INSTANCE-SPEC>",
        "    </SW-SYSTEM>",
        "  </SW-SYSTEMS>",
        "</MSRSW>",
        "",
    ]
    return "\n".join(out)


def _long_name(m: dict[str, Any], order_maps: list[dict[str, Any]], interpolation_text: str) -> str:
    orders = ", ".join(str(om["harmonic_order"]) for om in order_maps)
    return (
        f"ripplecal LUT, map {m['id']}, orders {orders}, method {m['method']}, bench {m['bench_identity']}, "
        f"software {__version__}; v_inj = theta_cos cos(h phi_e) + theta_sin sin(h phi_e), rad; "
        f"LUT interpolation: {interpolation_text}"
    )


def _instance(
    order: int,
    kind: str,
    unit: str,
    udc_v: float,
    torque: list[float],
    speed: list[float],
    plane: list[list[float]],
    counts: dict[str, int],
    date: str,
) -> list[str]:
    """One MAP instance: values[x = torque][y = speed] as one VG per torque breakpoint."""
    integer = unit == "-"

    def value(v: float) -> str:
        return str(int(v)) if integer else shortest_number(v)

    groups = [
        "                <VG>" + "".join(f"<V>{value(plane[j][i])}</V>" for j in range(len(speed))) + "</VG>"
        for i in range(len(torque))
    ]
    remark = (
        f"order {order}: {counts['ok']} ok, {counts['filled']} filled, {counts['none']} without an entry, "
        f"{counts['injection_off']} with injection off"
    )
    flags = [
        "              <SW-CS-FLAG>"
        f"<CATEGORY>{category}</CATEGORY><FLAG>{counts[key]}</FLAG><CSUS>ripplecal</CSUS></SW-CS-FLAG>"
        for category, key in (
            ("ok", "ok"),
            ("filled", "filled"),
            ("not_ok", "none"),
            ("injection_off", "injection_off"),
        )
    ]
    return [
        "          <SW-INSTANCE>",
        f"            <SHORT-NAME>{instance_name(order, kind, udc_v)}</SHORT-NAME>",
        f"            <LONG-NAME>{kind.lower()} of order {order} at U_dc = {udc_v:g} V</LONG-NAME>",
        "            <CATEGORY>MAP</CATEGORY>",
        "            <SW-VALUE-CONT>",
        f"              <UNIT-DISPLAY-NAME>{unit}</UNIT-DISPLAY-NAME>",
        f"              <SW-ARRAYSIZE><V>{len(torque)}</V><V>{len(speed)}</V></SW-ARRAYSIZE>",
        "              <SW-VALUES-PHYS>",
        *groups,
        "              </SW-VALUES-PHYS>",
        "            </SW-VALUE-CONT>",
        "            <SW-AXIS-CONTS>",
        *(
            "              <SW-AXIS-CONT><CATEGORY>STD_AXIS</CATEGORY>"
            f"<UNIT-DISPLAY-NAME>{axis_unit}</UNIT-DISPLAY-NAME><SW-ARRAYSIZE><V>{len(points)}</V></SW-ARRAYSIZE>"
            "<SW-VALUES-PHYS>"
            + "".join(f"<V>{shortest_number(p)}</V>" for p in points)
            + "</SW-VALUES-PHYS></SW-AXIS-CONT>"
            for axis_unit, points in (("Nm", torque), ("rpm", speed))
        ),
        "            </SW-AXIS-CONTS>",
        "            <SW-CS-HISTORY>",
        f"              <CS-ENTRY><STATE>{_state(counts)}</STATE><DATE>{date}</DATE><CSUS>ripplecal</CSUS>"
        f"<REMARK><P>{remark}</P></REMARK></CS-ENTRY>",
        "            </SW-CS-HISTORY>",
        "            <SW-CS-FLAGS>",
        *flags,
        "            </SW-CS-FLAGS>",
        "          </SW-INSTANCE>",
    ]
