"""The dashboard's layout at 1024 px and at full width (issue 30): every card screenshotted and checked in the
page (tests/browser/layout_checks.js) for text outside its box, labels on top of each other, a figure box with
nothing drawn and a page wider than the window.

The states a reader meets are seeded, not run: the service's own database gets paper-bench's refined map
(tests/data/refined_turn_map.json: non-uniform axes, cells down to 25 rpm and 0.125 N·m), the coarse map it was
refined from with its failed cells, both validated, and the refinement between them; another bench's sweep
waits in the queue (its row has its pause and cancel buttons); a schedule has fired; the bench status shows its
widest readings (the longest CiA 402 states, minutes-old values, a refused LUT download)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from tests.browser.conftest import _api
from tests.support.maps import make_map, store_sweep, theta_of

pytestmark = pytest.mark.browser

HERE = Path(__file__).resolve().parent
LAYOUT_CHECKS = (HERE / "layout_checks.js").read_text()
REFINED_TURN_MAP = HERE.parents[0] / "data" / "refined_turn_map.json"
WIDTHS = (1024, 1920)
# the source map of the refinement: every other breakpoint of the refined map's (all of them on its axes)
SOURCE_AXES = {
    "torque_nm": [1.0, 1.5, 2.0, 2.5, 3.0, 4.0],
    "speed_rpm": [1000.0, 1200.0, 1400.0, 1800.0, 2200.0, 2600.0],
    "udc_v": [12.0],
}
SOURCE_FAILED = {(4.0, 2600.0, 12.0), (3.0, 2600.0, 12.0)}  # beyond the envelope: listed as not ok
TARGET_DB = 30.0  # of the validations and the refinement
OTHER_BENCH = "bench-b"  # named by queued runs only: its service never comes, so they wait
CARDS = ("#lab", "#bench", "#sweeps", "#schedules", "#identify", "#runups", "#result", "#map", "#map-compare")


def _refined_turn_map():
    """Axes and {(torque, speed, udc): (status, theta_cos, theta_sin)} of paper-bench's refined map."""
    data = json.loads(REFINED_TURN_MAP.read_text())
    cells = {(t, n, u): (status, tc, ts) for t, n, u, status, tc, ts in data["cells"]}
    return data["axes"], cells


def _suppression_db(torque_nm: float, speed_rpm: float) -> float:
    """A plausible validation figure: about 40 dB, worst along the field-weakening turn (2000..2300 rpm)."""
    return 42.0 - 14.0 * math.exp(-(((speed_rpm - 2150.0) / 120.0) ** 2)) - 2.0 * abs(torque_nm - 2.5)


def _validate(storage, map_id: int, axes: dict) -> int:
    """A finished validation of map `map_id` as a validation job stores it: every point of the finer grid
    measured, but one that failed. Returns the validation's id."""
    from service.runs.validation import ValidationRun, store_validation, validation_points

    job_id = storage.create_job("validation", {"map_id": map_id, "force": True})
    storage.update_job(job_id, state="done")
    cells = []
    for k, (op, kind) in enumerate(validation_points(axes)):
        cell = {"operating_point": op.model_dump(), "kind": kind}
        if k == 1:
            cell.update(status="failed", error="MeasurementError: the drive left operation_enabled at the point")
        else:
            db = _suppression_db(op.torque_nm, op.speed_rpm)
            cell.update(status="measured", error=None, suppression_db=db, holds=db >= TARGET_DB, noise_floor_db=-55.0)
        cells.append(cell)
    run = ValidationRun(map_id=map_id, harmonic_order=6, options={"target_db": TARGET_DB}, cells=cells)
    run.download = {"crc32": "0x92E2D703", "bytes": 1873}
    return store_validation(storage, job_id, run, "test-bench")


def _round(storage, number: int, map_id: int, validation_id: int, inserted: dict, new_cells: int) -> dict:
    """A refinement round as the refinement records it, from the stored validation of its map."""
    v = storage.latest_validation(map_id)["summary"]
    return {
        "round": number,
        "map_id": map_id,
        "validation_id": validation_id,
        "points": v["points"],
        "below_target": v["points"] - v["held"],
        "grid_median_db": v["grid"]["median_db"],
        "midpoint_median_db": v["midpoint"]["median_db"],
        "min_db": v["min_db"],
        "inserted": inserted,
        "remeasured": len(SOURCE_FAILED) if number == 0 else 0,
        "new_cells": new_cells,
    }


def _seed(storage) -> dict:
    """The maps, validations, refinement and sweeps the panels show; {name: id}."""
    from service.maps.build import build_map
    from service.store.storage import now_iso

    axes, cells = _refined_turn_map()

    def theta(p):
        return cells[p][1:]

    # a map never validated: the validation figure has nothing to draw
    plain = make_map(
        storage,
        {"torque_nm": [1.0, 2.5], "speed_rpm": [1000.0, 2000.0], "udc_v": [12.0]},
        lambda p: theta_of(2.0 + p[0], 250.0 + p[1] / 100.0),
    )
    source = make_map(storage, SOURCE_AXES, theta, {p: "failed" for p in SOURCE_FAILED})
    source_validation = _validate(storage, source, SOURCE_AXES)
    # the refinement: its cells as results of its sweep, its map refined from the source
    refinement = store_sweep(storage, axes, theta, {p: c[0] for p, c in cells.items() if c[0] != "ok"})
    inserted = {k: sorted(set(axes[k]) - set(SOURCE_AXES[k])) for k in ("torque_nm", "speed_rpm")}
    new_cells = len(cells) - len(SOURCE_AXES["torque_nm"]) * len(SOURCE_AXES["speed_rpm"])
    cells_added = new_cells + len(SOURCE_FAILED)  # and the source's failed cells measured again
    refined = build_map(
        storage,
        axes,
        storage.sweep_results(refinement),
        refinement,
        6,
        "adaptive",
        "test-bench",
        refined_from=source,
        provenance={"refinement_id": refinement, "round": 1, "cells_added": cells_added, "lut_cells": "int16"},
    )
    refined_validation = _validate(storage, refined, axes)
    rounds = [
        _round(storage, 0, source, source_validation, inserted, new_cells),
        _round(storage, 1, refined, refined_validation, {}, 0),
    ]
    state = {
        "target_db": TARGET_DB,
        "max_cells": 400,
        "max_bytes": 2048,
        "validation": {"target_db": TARGET_DB},
        "phase": "done",
        "round": 1,
        "current_map_id": refined,
        "axes": axes,
        "pending": [],
        "cells_added": cells_added,
        "rounds": rounds,
        "plant_time_s": 1234.5,
        "stopped": f"the cell budget (max_cells 400) is spent: {rounds[-1]['below_target']} points of map {refined} "
        f"still below {TARGET_DB:g} dB, along the field-weakening turn 2000..2300 rpm at 1..1.75 N·m",
    }
    storage.update_sweep(
        refinement,
        kind="refinement",
        source_map_id=source,
        refinement=state,
        state="done",
        started_at=now_iso(),
        finished_at=now_iso(),
        map_id=refined,
    )
    return {"plain": plain, "source": source, "refined": refined, "refinement": refinement}


def _widest_status(real: dict) -> dict:
    """The service's own /bench/status answer with the widest readings it can carry: the longest CiA 402
    states, values of five digits and more, minutes old (struck through), a refused LUT download, DAQ
    overruns and an error naming an address."""
    s = json.loads(json.dumps(real))
    old = 125.0  # "2 min ago"
    s["drive"].update(state="not_ready_to_switch_on", speed_rpm=-12345.6, torque_nm=-12.345, udc_v=600.25)
    s["drive"]["ages"] = {k: old for k in ("state", "speed_rpm", "torque_nm", "udc_v")}
    s["load"].update(state="fault_reaction_active", speed_rpm=-12345.6)
    s["load"]["ages"] = {k: old for k in ("state", "speed_rpm")}
    s["lut"].update(map_id=12345, crc32="0x92E2D703", status="last_download_refused", ages={"status": old})
    s["daq"].update(
        frames=1234567890,
        crc_failures=12345,
        sequence_gaps=6789,
        flush_resyncs=123,
        overruns=45,
        overrun_samples_lost=1234567,
        data_age_s=old,
    )
    s["run"] = {
        **(s.get("run") or {}),
        "speed_rpm": -12345.6,
        "harmonic_amplitude_fs": 0.123456,
        "plant_time_s": 12345.67,
        "ages": {"speed_rpm": old, "harmonic_amplitude_fs": old},
    }
    s["accel_full_scale_rad_s2"] = 5000.0
    s["error"] = (
        "drive: no answer to SDO 0x6041:0 within 0.5 s on socketcand://127.0.0.1:29536/vcan0 "
        "(node 5, CiA 402 statusword)"
    )
    return s


@pytest.fixture(scope="module")
def seeded(service):
    """The service's database seeded (_seed), and another bench's runs queued through the API: a sweep of many
    values (its row: pause, cancel, what it waits for) and a schedule that has fired."""
    from service.store.storage import Storage

    storage = Storage(service["log"].parent / "ripplecal.db")  # the service's own database (WAL)
    ids = _seed(storage)
    grid = {"torque_nm": [0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0], "speed_rpm": [1000, 1500, 2000], "udc_v": [12]}
    ids["waiting"] = _api(service, "POST", "/sweeps", {"grid": grid, "method": "adaptive", "bench": OTHER_BENCH})["id"]
    schedule = _api(
        service,
        "POST",
        "/schedules",
        {
            "name": "nightly map of the refined grid",
            "cron": "0 2 * * 1-5",
            "timezone": "Europe/Berlin",
            "sweep": {"grid": grid, "method": "adaptive"},
            "bench": OTHER_BENCH,
        },
    )
    for due, outcome, sweep, note in (
        ("2026-03-02T01:00:00Z", "started", ids["source"], None),
        ("2026-03-03T01:00:00Z", "skipped", None, f"the bench was busy with sweep {ids['source']}"),
        ("2026-03-04T01:00:00Z", "missed", None, "the service was not running at 02:00 Europe/Berlin"),
    ):
        storage.insert_schedule_run(schedule["id"], due, due, outcome, sweep, note)
    return ids


def _check(page, card: str, shot: Path) -> dict:
    """layout_checks.js on one card, after a screenshot of it: its findings, none when it is laid out well."""
    page.locator(card).screenshot(path=str(shot))
    return {k: v for k, v in page.evaluate(LAYOUT_CHECKS, card).items() if v}


def _summary(findings: dict, shown: int = 4) -> str:
    """Per card and check: how many findings, the first few of them."""
    lines = []
    for card, checks in findings.items():
        for check, items in checks.items():
            lines.append(f"{card} {check}: {len(items)}")
            lines += [f"    {json.dumps(item, ensure_ascii=False)}" for item in items[:shown]]
    return "\n".join(lines)


@pytest.mark.parametrize("width", WIDTHS)
def test_every_card_fits_the_window_and_no_labels_overlap(service, browser, seeded, width, tmp_path):
    """At `width` x 1000 px: the bench status at its widest, the sweep form with its preview, the sweeps (one
    waiting, one with its non-ok points open), the schedules, the refined map (non-uniform axes) with its
    validation and its refinement beside the source's, the comparison with the source; then a map never
    validated. Every card: no text outside its box, no labels on top of each other, no empty figure box, no
    horizontal scroll."""
    base, ids = service["base"], seeded
    context = browser.new_context(viewport={"width": width, "height": 1000})
    page = context.new_page()
    pageerrors = []
    page.on("pageerror", lambda e: pageerrors.append(str(e)))

    def widest_status(route):
        answer = route.fetch()
        route.fulfill(response=answer, json=_widest_status(answer.json()))

    # the status polled (SSE refused: its bench.status events would bring the real readings back)
    page.route("**/api/v1/events", lambda route: route.fulfill(status=503, body="polled in this test"))
    page.route("**/api/v1/bench/status", widest_status)
    findings = {}
    try:
        page.goto(base + "/", wait_until="load")
        page.wait_for_function(
            """(ids) => {
                const q = (s) => document.querySelector(s);
                const drawn = (id) => Boolean(q(`#${id} .main-svg`));
                return q('[data-testid="drive-state"]').textContent === 'not_ready_to_switch_on'
                    && q('[data-testid="lab-row"][data-bench="bench-b"]')
                    && q(`[data-sweep-id="${ids.source}"] [data-testid="sweep-attention"]`)
                    && q(`[data-sweep-id="${ids.waiting}"]`)
                    && q('[data-testid="schedule-run"]')
                    && q('[data-testid="map-select"]').value === String(ids.refined)
                    && ['plot-gamma', 'plot-delta', 'plot-supp', 'plot-validation'].every(drawn)
                    && !q('[data-testid="refine-outcome"]').hidden
                    && q('[data-testid="validation-heatmap-refined"]').dataset.mapId === String(ids.refined)
                    && ['plot-refine-source', 'plot-refine-refined'].every(drawn);
            }""",
            arg=ids,
            timeout=30_000,
        )
        page.click(f'[data-sweep-id="{ids["source"]}"] [data-testid="sweep-attention"] summary')
        page.check('[data-testid="sweep-regime"]')
        page.click('[data-testid="sweep-preview-btn"]')
        page.wait_for_selector('[data-testid="sweep-preview"]:not([hidden])', timeout=10_000)
        page.select_option('[data-testid="compare-b"]', str(ids["source"]))
        page.wait_for_selector("#plot-compare-supp .main-svg", timeout=10_000)
        for card in CARDS:
            found = _check(page, card, tmp_path / f"{width}_{card[1:]}.png")
            if found:
                findings[card] = found
        # a cell of the refined map opens its result (no traces stored: its numbers and facts)
        page.locator("#plot-gamma").scroll_into_view_if_needed()
        x, y = page.evaluate("""() => {
            const gd = document.getElementById('plot-gamma');
            const { xaxis, yaxis } = gd._fullLayout;
            const box = gd.getBoundingClientRect();
            return [box.left + xaxis._offset + xaxis.l2p(4), box.top + yaxis._offset + yaxis.l2p(1000)];
        }""")
        page.mouse.click(x, y)
        page.wait_for_selector('[data-testid="result-view"][data-empty=""]', timeout=10_000)
        found = _check(page, "#result", tmp_path / f"{width}_result_of_a_cell.png")
        if found:
            findings["#result, a cell's"] = found
        # a map never validated: nothing drawn under "Validate on drive"
        page.select_option('[data-testid="map-select"]', str(ids["plain"]))
        page.wait_for_function(
            """() => /Not validated/.test(document.querySelector('[data-testid="validation-meta"]').textContent)""",
            timeout=10_000,
        )
        found = _check(page, "#map", tmp_path / f"{width}_map_not_validated.png")
        if found:
            findings["#map, a map never validated"] = found
        page.screenshot(path=str(tmp_path / f"{width}_page.png"), full_page=True)
    finally:
        page.unroute_all(behavior="ignoreErrors")  # a status poll in flight as the page closes
        context.close()
    assert not pageerrors, pageerrors
    (tmp_path / f"{width}_findings.json").write_text(json.dumps(findings, indent=1))
    assert not findings, f"at {width} px (all of it and the screenshots in {tmp_path}):\n" + _summary(findings)
