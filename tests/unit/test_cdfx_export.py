"""CDFX (ASAM CDF 2.0) export: valid against the CDF 2.0.0 DTD as published (tests/support/cdf_schema.py: fetched
from the package registry by the test set-up) and read back by an independent parser (the standard library's
ElementTree) to the same numbers as the closed forms the maps are made of (tests/unit/test_lut_readers.py's
refined map with filled cells and a hole; tests/unit/test_lut_orders.py's map of orders 6 and 12), never the
exporter's own output."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import pytest
from lxml import etree

from service.maps.lut_export import EXPORT_FORMATS, export_map
from tests.support.cdf_schema import cdf_dtd
from tests.unit import test_lut_orders as two
from tests.unit import test_lut_readers as refined


@pytest.fixture(scope="module")
def dtd():
    return etree.DTD(str(cdf_dtd()))


def _instances(text: str) -> dict[str, ET.Element]:
    root = ET.fromstring(text.encode())
    assert root.tag == "MSRSW" and root.findtext("CATEGORY") == "CDF20"
    return {i.findtext("SHORT-NAME"): i for i in root.iter("SW-INSTANCE")}


def _read(instance: ET.Element) -> tuple[list[float], list[float], dict[tuple[float, float], float]]:
    """(torque axis, speed axis, {(torque, speed): value}) of a MAP instance: one VG per torque breakpoint."""
    assert instance.findtext("CATEGORY") == "MAP"
    x_axis, y_axis = instance.findall("SW-AXIS-CONTS/SW-AXIS-CONT")
    xs = [float(v.text) for v in x_axis.findall("SW-VALUES-PHYS/V")]
    ys = [float(v.text) for v in y_axis.findall("SW-VALUES-PHYS/V")]
    assert (x_axis.findtext("UNIT-DISPLAY-NAME"), y_axis.findtext("UNIT-DISPLAY-NAME")) == ("Nm", "rpm")
    size = [int(v.text) for v in instance.findall("SW-VALUE-CONT/SW-ARRAYSIZE/V")]
    assert size == [len(xs), len(ys)]
    groups = instance.findall("SW-VALUE-CONT/SW-VALUES-PHYS/VG")
    assert len(groups) == len(xs)
    values = {(x, y): float(v.text) for x, g in zip(xs, groups) for y, v in zip(ys, g.findall("V"))}
    return xs, ys, values


def test_cdfx_is_a_registered_export_format():
    assert EXPORT_FORMATS["cdfx"].extension == "cdfx" and EXPORT_FORMATS["cdfx"].media_type == "application/xml"


def test_the_refined_map_is_valid_cdf_and_reads_back_to_its_closed_form(dtd):
    text = export_map(refined.refined_map(), "cdfx")
    doc = etree.fromstring(text.encode())
    assert dtd.validate(doc), dtd.error_log.filter_from_errors()
    instances = _instances(text)
    kinds = ("THETA_COS", "THETA_SIN", "GAMMA", "DELTA", "VALID", "FILLED", "INJECTION_OFF")
    assert set(instances) == {f"RIPPLECAL_H6_{k}_U{u}V" for k in kinds for u in (12, 24)}
    for u in (12.0, 24.0):
        name = f"U{u:g}V"
        xs, ys, cos = _read(instances[f"RIPPLECAL_H6_THETA_COS_{name}"])
        assert xs == refined.AXES["torque_nm"] and ys == refined.AXES["speed_rpm"]  # non-uniform, as they are
        _, _, sin = _read(instances[f"RIPPLECAL_H6_THETA_SIN_{name}"])
        _, _, gamma = _read(instances[f"RIPPLECAL_H6_GAMMA_{name}"])
        _, _, valid = _read(instances[f"RIPPLECAL_H6_VALID_{name}"])
        _, _, filled = _read(instances[f"RIPPLECAL_H6_FILLED_{name}"])
        for (t, n), c in cos.items():
            p = (t, n, u)
            want = (0.0, 0.0) if p == refined.HOLE else refined.theta(*p)
            assert (c, sin[(t, n)]) == pytest.approx(want, abs=1e-15), p
            assert gamma[(t, n)] == pytest.approx(math.degrees(math.hypot(*want)), abs=1e-12)
            assert valid[(t, n)] == (0 if p in refined.FILLED or p == refined.HOLE else 1)
            assert filled[(t, n)] == (1 if p in refined.FILLED else 0)
    # per instance: how far it is calibrated and the cells by class
    theta = instances["RIPPLECAL_H6_THETA_COS_U12V"]
    assert theta.findtext("SW-CS-HISTORY/CS-ENTRY/STATE") == "incomplete"  # the hole: a cell without an entry
    flags = {f.findtext("CATEGORY"): int(f.findtext("FLAG")) for f in theta.findall("SW-CS-FLAGS/SW-CS-FLAG")}
    assert flags == {"ok": 27, "filled": 2, "not_ok": 1, "injection_off": 0}


def test_the_two_order_map_is_valid_cdf_with_each_order_its_own(dtd):
    text = export_map(two.two_order_map(), "cdfx")
    assert dtd.validate(etree.fromstring(text.encode())), dtd.error_log.filter_from_errors()
    instances = _instances(text)
    for h in (6, 12):
        _, _, cos = _read(instances[f"RIPPLECAL_H{h}_THETA_COS_U12V"])
        for (t, n), c in cos.items():
            want = 0.0 if (h == 6 and (t, n, 12.0) == two.HOLE_6) else two.theta(h, t, n, 12.0)[0]
            assert c == pytest.approx(want, abs=1e-15), (h, t, n)
    states = {h: instances[f"RIPPLECAL_H{h}_VALID_U12V"].findtext("SW-CS-HISTORY/CS-ENTRY/STATE") for h in (6, 12)}
    assert states == {6: "incomplete", 12: "preliminary"}  # the 6th has a hole, the 12th a fill


def test_a_document_the_dtd_refuses_is_caught(dtd):
    """The check itself is real: a MAP instance without its SHORT-NAME is not CDF 2.0."""
    text = export_map(two.two_order_map(), "cdfx").replace("<SHORT-NAME>RIPPLECAL_H12_GAMMA_U12V</SHORT-NAME>", "", 1)
    assert not dtd.validate(etree.fromstring(text.encode()))
