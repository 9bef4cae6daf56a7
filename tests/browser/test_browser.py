"""Browser test of the dashboard against the real service (which starts the emulated bench).

Runs Debian's Chromium (/usr/bin/chromium) through Python Playwright; never downloads a browser.
Outside CI the test is skipped when Chromium or Playwright is missing; in CI (env CI set) it fails.
"""

from __future__ import annotations

import json
import re
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from tests.browser.conftest import _api, _log_tail
from tests.support.operating_points import OP1
from tests.support.waiting import wait_until

pytestmark = pytest.mark.browser

REPO = Path(__file__).resolve().parents[2]
WEB_MODULES = REPO / "web" / "js"
DRIVE_STATES = re.compile(
    r"^(not_ready_to_switch_on|switch_on_disabled|ready_to_switch_on|switched_on|"
    r"operation_enabled|quick_stop_active|fault_reaction_active|fault)$"
)
NUMBER = r"/^-?\d+(\.\d+)?$/"


def _open(browser, base):
    """A fresh page on the dashboard that records console errors, page errors and requests."""
    context = browser.new_context(viewport={"width": 1600, "height": 1000})
    page = context.new_page()
    rec = {"console": [], "pageerrors": [], "requests": [], "failed": [], "responses": {}}
    page.on("console", lambda m: rec["console"].append(f"{m.type}: {m.text}") if m.type == "error" else None)
    page.on("pageerror", lambda e: rec["pageerrors"].append(str(e)))
    page.on("request", lambda r: rec["requests"].append(r.url))
    page.on("requestfailed", lambda r: rec["failed"].append(f"{r.url}: {r.failure}"))
    page.on("response", lambda r: rec["responses"].__setitem__(r.url, (r.status, r.headers.get("content-type", ""))))
    page.goto(base + "/", wait_until="load")
    return context, page, rec


def test_dashboard_shows_live_bench_status(service, browser, tmp_path):
    base = service["base"]
    context, page, rec = _open(browser, base)
    try:
        try:
            # drive state: one of the CiA 402 states
            page.wait_for_function(
                """(re) => {
                    const el = document.querySelector('[data-testid="drive-state"]');
                    return el && new RegExp(re).test(el.textContent.trim());
                }""",
                arg=DRIVE_STATES.pattern,
                timeout=30_000,
            )
            # DC-link voltage and speed filled with numbers
            page.wait_for_function(
                f"""() => ['drive-udc', 'drive-speed'].every((id) => {{
                    const el = document.querySelector(`[data-testid="${{id}}"]`);
                    return el && {NUMBER}.test(el.textContent.trim());
                }})""",
                timeout=30_000,
            )
        except Exception:
            page.screenshot(path=str(tmp_path / "dashboard_failure.png"), full_page=True)
            raise AssertionError(
                "bench status not shown: drive-state=%r drive-udc=%r drive-speed=%r\nconsole: %s\nservice log:\n%s"
                % (
                    page.text_content('[data-testid="drive-state"]'),
                    page.text_content('[data-testid="drive-udc"]'),
                    page.text_content('[data-testid="drive-speed"]'),
                    rec["console"] + rec["pageerrors"],
                    _log_tail(service["log"]),
                )
            )

        state = page.text_content('[data-testid="drive-state"]').strip()
        assert DRIVE_STATES.match(state), state
        udc = float(page.text_content('[data-testid="drive-udc"]'))
        speed = float(page.text_content('[data-testid="drive-speed"]'))
        # the supply output is OFF while the bench is idle (the safe state), so 0 V is a valid reading
        assert 0.0 <= udc < 1000.0, f"implausible DC-link voltage {udc} V"
        assert abs(speed) < 100_000.0, f"implausible speed {speed} rpm"
        assert page.text_content('[data-testid="bench-connected"]').strip() in ("yes", "no")

        # Plotly comes from the service itself, not from a CDN
        assert page.evaluate("typeof window.Plotly") == "object", "window.Plotly undefined: /vendor/plotly.min.js"
        assert any(u == base + "/vendor/plotly.min.js" for u in rec["requests"]), rec["requests"]

        # the sweep and map sections loaded without error
        page.wait_for_selector('[data-testid="sweep-table"]', state="attached")
        assert page.is_hidden('[data-testid="sweep-error"]')

        # the SSE stream delivers events (the page goes live), then check the page stayed clean
        try:
            page.wait_for_function(
                """() => document.querySelector('[data-testid="live-mode"]').dataset.mode === 'live'""", timeout=30_000
            )
        except Exception:
            raise AssertionError(
                "no bench.status received over SSE /api/v1/events (dashboard fell back to polling): "
                "live-mode %r" % page.get_attribute('[data-testid="live-mode"]', "data-mode")
            )
        foreign = [u for u in rec["requests"] if not u.startswith(base + "/") and not u.startswith(("data:", "blob:"))]
        assert not foreign, f"requests outside the service: {foreign}"
        assert not rec["pageerrors"], f"JavaScript errors: {rec['pageerrors']}"
        assert not rec["console"], f"console errors: {rec['console']}"
        assert not [f for f in rec["failed"] if "/api/v1/events" not in f], rec["failed"]
        page.screenshot(path=str(tmp_path / "dashboard.png"), full_page=True)
    finally:
        context.close()


def test_dashboard_loads_every_module_as_javascript_without_errors(service, browser):
    """index.html loads web/js/main.js as an ES module; it imports every other module under web/js,
    each served with a JavaScript MIME type (browsers refuse a module script otherwise), and the
    page runs without console errors or uncaught exceptions."""
    base = service["base"]
    expected = {base + "/static/js/" + f.relative_to(WEB_MODULES).as_posix() for f in WEB_MODULES.rglob("*.js")}
    assert base + "/static/js/main.js" in expected
    context, page, rec = _open(browser, base)
    try:
        assert page.evaluate("document.querySelector('script[src=\"/static/js/main.js\"]').type") == "module"
        # main.js's init() ran: the live indicator left "connecting", the Identify panel set its example
        try:
            page.wait_for_function(
                """() => document.querySelector('[data-testid="live-mode"]').dataset.mode !== 'connecting'
                    && document.querySelector('[data-testid="identify-options"]').placeholder.includes('mu_per_s')""",
                timeout=15_000,
            )
        except Exception:
            raise AssertionError(
                "the modules did not start the page:\nJavaScript errors: %s\nconsole errors: %s\n"
                "failed requests: %s" % (rec["pageerrors"], rec["console"], rec["failed"])
            )
        loaded = {u: v for u, v in rec["responses"].items() if u.startswith(base + "/static/js/")}
        missing = sorted(expected - set(loaded))
        assert not missing, f"modules under web/js never loaded by the page (dead or not imported): {missing}"
        for url, (status, ctype) in loaded.items():
            assert status in (200, 304), f"{url}: HTTP {status}"
            assert ctype.split(";")[0].strip() in ("text/javascript", "application/javascript"), f"{url}: {ctype!r}"
        page.wait_for_timeout(1500)  # deliberately: the started page runs a while (a late error shows)
        assert not rec["pageerrors"], f"JavaScript errors: {rec['pageerrors']}"
        assert not rec["console"], f"console errors: {rec['console']}"
    finally:
        context.close()


def test_sweep_form_without_token_shows_auth_error(service, browser):
    """A grid the form cannot read is named; POST /sweeps without a token is refused (nothing moves);
    the page says why."""
    context, page, rec = _open(browser, service["base"])
    try:
        page.evaluate("localStorage.removeItem('ripplecal.token')")
        page.fill('[data-testid="token"]', "")
        # a grid the form cannot read is named before anything is sent
        page.fill('[data-testid="sweep-torque"]', "1, x")
        page.fill('[data-testid="sweep-speed"]', "")
        page.click('[data-testid="sweep-submit"]')
        err = page.locator('[data-testid="sweep-error"]')
        err.wait_for(state="visible", timeout=10_000)
        assert (
            'torque: "x" is not a number' in err.inner_text() and "speed: enter at least one number" in err.inner_text()
        )
        page.fill('[data-testid="sweep-torque"]', "1")
        page.fill('[data-testid="sweep-speed"]', "1000")
        page.fill('[data-testid="sweep-udc"]', "12")
        page.click('[data-testid="sweep-submit"]')
        page.wait_for_function(
            """() => document.querySelector('[data-testid="sweep-error"]')
                                        .innerText.includes('token missing or invalid')""",
            timeout=10_000,
        )
        assert err.is_visible()
        assert page.is_hidden('[data-testid="sweep-ok"]')
        # with a token, a grid outside this bench's limits: every bad field on a line of its own, with the
        # limit that applies here, in the service's words (issue 30: only the first, in the library's)
        page.fill('[data-testid="token"]', service["token"])
        page.fill('[data-testid="sweep-torque"]', "1, 9")
        page.fill('[data-testid="sweep-speed"]', "50, 1e9")
        page.click('[data-testid="sweep-submit"]')
        page.wait_for_function(
            """() => document.querySelector('[data-testid="sweep-error"]').innerText.includes('HTTP 422')""",
            timeout=10_000,
        )
        said = err.inner_text()
        assert "grid.torque_nm: torque_nm 9 exceeds the limit of 5 Nm" in said, said
        assert "grid.speed_rpm: speed_rpm 50 is below the minimum of 100 rpm" in said, said
        assert "speed_rpm 1e+09 exceeds the limit of 6000 rpm" in said, said
        assert "pydantic" not in said and "Input should" not in said, said
        assert not rec["pageerrors"], rec["pageerrors"]
        # the refused POSTs are the only console errors (Chromium logs every failed fetch)
        assert all(any(code in m for code in ("401", "403", "422")) for m in rec["console"]), rec["console"]
    finally:
        context.close()


IDENTIFY_TIMEOUT_MS = 90_000
RESULT_PLOTS = ("plot-theta", "plot-amplitude", "plot-spectrum", "plot-alpha")  # Fig. 9 (2), Fig. 10 (2)


def test_identify_panel_runs_probe_and_shows_result(service, browser, tmp_path):
    """One probe identification through the Identify panel; the result view draws Fig. 9 and Fig. 10."""
    context, page, rec = _open(browser, service["base"])
    try:
        page.fill('[data-testid="token"]', service["token"])
        page.fill('[data-testid="identify-torque"]', "2.5")
        page.fill('[data-testid="identify-speed"]', "2000")
        page.fill('[data-testid="identify-udc"]', "12")
        page.select_option('[data-testid="identify-method"]', "probe")
        page.fill('[data-testid="identify-options"]', "")
        page.click('[data-testid="identify-submit"]')
        try:
            page.locator('[data-testid="identify-job"]').wait_for(state="visible", timeout=10_000)
            page.wait_for_function(
                """() => {
                    const s = document.querySelector('[data-testid="identify-state"]');
                    return s && ['done', 'failed', 'cancelled'].includes(s.dataset.state);
                }""",
                timeout=IDENTIFY_TIMEOUT_MS,
            )
        except Exception:
            page.screenshot(path=str(tmp_path / "identify_failure.png"), full_page=True)
            err = page.locator('[data-testid="identify-error"]')
            raise AssertionError(
                "identification did not finish: job=%r error=%r\nconsole: %s\nservice log:\n%s"
                % (
                    page.text_content('[data-testid="identify-job"]'),
                    err.inner_text() if err.is_visible() else None,
                    rec["console"] + rec["pageerrors"],
                    _log_tail(service["log"]),
                )
            )
        state = page.get_attribute('[data-testid="identify-state"]', "data-state")
        assert state == "done", (
            f"job {state}: {page.text_content('[data-testid=identify-note]')}; "
            f"{page.text_content('[data-testid=identify-error]')}\nservice log:\n{_log_tail(service['log'])}"
        )
        assert page.is_hidden('[data-testid="identify-error"]'), page.inner_text('[data-testid="identify-error"]')

        # the result view shows this job's result, with its numbers
        page.wait_for_function(
            """(ids) => ids.every((id) => {
                const gd = document.querySelector(`[data-testid="${id}"]`);
                return gd && gd.classList.contains('js-plotly-plot') && Array.isArray(gd.data) && gd.data.length > 0;
            })""",
            arg=list(RESULT_PLOTS),
            timeout=10_000,
        )
        assert page.inner_text('[data-testid="result-status"]').strip() == "ok"
        assert "probe" in page.inner_text('[data-testid="result-title"]')
        nums = {k: page.inner_text(f'[data-testid="result-{k}"]').strip() for k in ("gamma", "delta", "suppression")}
        for k, v in nums.items():
            assert re.fullmatch(r"-?\d+(\.\d+)?", v), f"result-{k} shows {v!r}"
        assert 0.0 < float(nums["gamma"]) <= 15.0, nums  # gamma_max default 15 deg
        assert -360.0 <= float(nums["delta"]) <= 360.0, nums
        assert float(nums["suppression"]) > 0.0, nums

        # Fig. 9: theta_cos / theta_sin and the h-th amplitude over plant time, drawn with points
        points = page.evaluate(
            """(ids) => Object.fromEntries(ids.map((id) => {
                const gd = document.querySelector(`[data-testid="${id}"]`);
                return [id, gd.data.map((t) => (t.y || []).length)];
            }))""",
            list(RESULT_PLOTS),
        )
        assert len(points["plot-theta"]) == 2 and min(points["plot-theta"]) >= 2, points
        assert points["plot-amplitude"][0] >= 2, points
        assert (
            page.evaluate("document.querySelector('[data-testid=\"plot-amplitude\"]')._fullLayout.yaxis.type") == "log"
        )
        # Fig. 10: orders 1..24 before and after as bars; the alpha snippets before and after
        assert points["plot-spectrum"] == [24, 24], points
        assert len(points["plot-alpha"]) == 2 and min(points["plot-alpha"]) > 10, points
        assert page.locator('[data-testid="plot-spectrum"] .barlayer .trace').count() == 2
        assert page.locator('[data-testid="plot-theta"] .scatterlayer .trace').count() == 2
        # Fig. 8 belongs to the grid method only
        assert page.is_hidden('[data-testid="plot-grid"]')
        # axis titles carry units
        titles = page.evaluate(
            """(ids) => ids.map((id) => {
                const fl = document.querySelector(`[data-testid="${id}"]`)._fullLayout;
                return [fl.xaxis.title.text, fl.yaxis.title.text];
            })""",
            list(RESULT_PLOTS),
        )
        for xt, yt in titles:
            assert "(" in xt and "(" in yt, titles

        # the raw recording (issue 11): a download link, and what it links to is an MDF 4 file
        link = page.locator('[data-testid="result-recording-link"]')
        assert link.inner_text() == "raw recording (MF4)"
        href = link.get_attribute("href")
        assert re.fullmatch(r"/api/v1/results/\d+/recording\?format=mf4", href), href
        magic = page.evaluate(
            """(href) => fetch(href).then((r) => r.arrayBuffer())
            .then((b) => String.fromCharCode(...new Uint8Array(b.slice(0, 8))))""",
            href,
        )
        assert magic == "MDF     ", magic

        assert not rec["pageerrors"], f"JavaScript errors: {rec['pageerrors']}"
        assert not rec["console"], f"console errors: {rec['console']}"
        page.screenshot(path=str(tmp_path / "identify.png"), full_page=True)
    finally:
        context.close()


SWEEP_TIMEOUT_MS = 120_000


def test_sweep_from_the_form_shows_its_map_and_a_cell_opens_its_result(service, browser, tmp_path):
    """The panels meet only through events and main.js: a sweep started in the Sweeps panel reports
    progress over SSE, its finished map comes up in the Map panel, and a click on a map cell opens
    that cell's result in the result view."""
    context, page, rec = _open(browser, service["base"])
    try:
        # progress comes over SSE; a sweep that finishes before the stream is open would be missed
        # (the list is polled only while SSE is down), so start it once the page is live
        page.wait_for_function(
            """() => document.querySelector('[data-testid="live-mode"]').dataset.mode === 'live'""", timeout=15_000
        )
        page.fill('[data-testid="token"]', service["token"])
        page.fill('[data-testid="sweep-torque"]', "2.5")
        page.fill('[data-testid="sweep-speed"]', "2000")
        page.fill('[data-testid="sweep-udc"]', "12")
        page.select_option('[data-testid="sweep-method"]', "probe")
        page.click('[data-testid="sweep-submit"]')
        ok = page.locator('[data-testid="sweep-ok"]')
        ok.wait_for(state="visible", timeout=10_000)
        sweep_id = re.search(r"Sweep (\d+) accepted", ok.inner_text()).group(1)
        row = f'[data-testid="sweep-row"][data-sweep-id="{sweep_id}"]'
        try:
            page.wait_for_function(
                f"""() => {{
                    const r = document.querySelector('{row}');
                    return r && ['done', 'failed', 'cancelled'].includes(r.dataset.state);
                }}""",
                timeout=SWEEP_TIMEOUT_MS,
            )
            assert page.get_attribute(row, "data-state") == "done", page.inner_text(row)
            # the Map panel brings up the sweep's map by itself (sweep.progress done -> map)
            page.wait_for_function(
                """() => /finished — showing its map/.test(document.querySelector('[data-testid="map-note"]').textContent)
                    && document.querySelector('[data-testid="plot-gamma"]').classList.contains('js-plotly-plot')""",
                timeout=15_000,
            )
        except Exception:
            page.screenshot(path=str(tmp_path / "sweep_failure.png"), full_page=True)
            raise AssertionError(
                "sweep or its map not shown: row=%r map-note=%r\nconsole: %s\nservice log:\n%s"
                % (
                    page.text_content(row),
                    page.text_content('[data-testid="map-note"]'),
                    rec["console"] + rec["pageerrors"],
                    _log_tail(service["log"]),
                )
            )
        map_link = page.locator(f"{row} .map-cell a")
        map_id = map_link.inner_text().split()[-1]
        assert page.input_value('[data-testid="map-select"]') == map_id
        assert "1 cells (" in page.inner_text('[data-testid="map-meta"]')
        # the row's map link selects that map (Sweeps panel -> Map panel, through main.js)
        map_link.click()
        assert page.input_value('[data-testid="map-select"]') == map_id

        # one cell, so the middle of the plot area is that cell
        page.locator('[data-testid="plot-gamma"] .nsewdrag').first.click()
        page.wait_for_function(
            """() => /from map/.test(document.querySelector('[data-testid="result-title"]').textContent)""",
            timeout=10_000,
        )
        assert page.inner_text('[data-testid="result-status"]').strip() in (
            "ok",
            "below_target",
            "no_authority",
            "failed",
        )
        assert "probe" in page.inner_text('[data-testid="result-title"]')
        assert page.get_attribute('[data-testid="result-view"]', "data-empty") == ""
        assert not rec["pageerrors"], f"JavaScript errors: {rec['pageerrors']}"
        assert not rec["console"], f"console errors: {rec['console']}"
        page.screenshot(path=str(tmp_path / "sweep_map_result.png"), full_page=True)
    finally:
        context.close()


def test_dashboard_polls_bench_status_and_sweeps_while_sse_is_refused(service, browser):
    """events.js: without the SSE stream the page polls /bench/status (every 2 s) and the sweep list
    (every 5 s), says so in the live indicator, and the panels fill as they do over SSE."""
    base = service["base"]
    context = browser.new_context(viewport={"width": 1600, "height": 1000})
    page = context.new_page()
    pageerrors, polls = [], []
    page.on("pageerror", lambda e: pageerrors.append(str(e)))
    page.on("request", lambda r: polls.append((time.monotonic(), r.url)))
    try:
        page.route("**/api/v1/events", lambda route: route.fulfill(status=503, body="no stream in this test"))
        page.goto(base + "/", wait_until="load")
        page.wait_for_function(
            """() => document.querySelector('[data-testid="live-mode"]').dataset.mode === 'poll'""", timeout=10_000
        )
        assert page.inner_text('[data-testid="live-mode"]').strip() == "polling every 2 s"
        assert DRIVE_STATES.match(page.text_content('[data-testid="drive-state"]').strip())
        start = time.monotonic()

        def since_start(url: str) -> list[float]:
            return [t for t, u in polls if t >= start and u == url]

        def polled() -> bool:
            page.wait_for_timeout(100)  # Playwright delivers the request events while it waits
            return (
                len(since_start(base + "/api/v1/bench/status")) >= 3 and len(since_start(base + "/api/v1/sweeps")) >= 1
            )

        wait_until(polled, 30, "three status polls and one sweep-list poll", poll_s=0)
        status_polls = since_start(base + "/api/v1/bench/status")
        # every 2 s: two intervals take about 4 s (neither a burst nor a stall)
        assert 2.6 <= status_polls[2] - status_polls[0] <= 6.5, status_polls
        assert page.get_attribute('[data-testid="live-mode"]', "data-mode") == "poll"
        assert not pageerrors, pageerrors
    finally:
        context.close()


def test_schedule_created_in_the_panel_shows_its_next_runs_and_can_be_turned_off(service, browser, tmp_path):
    """The Schedules panel: a schedule made from the form appears with its next runs (cron read in its
    IANA zone), is turned off with its checkbox (no next runs) and deleted with its button."""
    context, page, rec = _open(browser, service["base"])
    try:
        page.fill('[data-testid="token"]', service["token"])
        page.fill('[data-testid="schedule-name"]', "browser nightly")
        page.fill('[data-testid="schedule-cron"]', "30 2 * * *")
        page.fill('[data-testid="schedule-timezone"]', "Europe/Berlin")
        page.fill('[data-testid="schedule-torque"]', "2.5")
        page.fill('[data-testid="schedule-speed"]', "2000")
        page.fill('[data-testid="schedule-udc"]', "12")
        page.select_option('[data-testid="schedule-method"]', "probe")
        page.click('[data-testid="schedule-submit"]')
        ok = page.locator('[data-testid="schedule-ok"]')
        try:
            ok.wait_for(state="visible", timeout=10_000)
        except Exception:
            page.screenshot(path=str(tmp_path / "schedule_failure.png"), full_page=True)
            raise AssertionError(
                "schedule not accepted: %r\nconsole: %s"
                % (page.text_content('[data-testid="schedule-error"]'), rec["console"] + rec["pageerrors"])
            )
        schedule_id = re.search(r"Schedule (\d+) \(browser nightly\) added", ok.inner_text()).group(1)
        row = f'[data-testid="schedule-row"][data-schedule-id="{schedule_id}"]'
        page.wait_for_selector(row, timeout=10_000)
        assert page.get_attribute(row, "data-enabled") == "true"
        next_runs = page.inner_text(f"{row} [data-testid=schedule-next]").split("\n")
        assert len(next_runs) == 3 and all(re.search(r"02:30:00\+0[12]:00$|03:00:00\+02:00$", t) for t in next_runs), (
            next_runs
        )
        assert page.inner_text(f"{row} [data-testid=schedule-runs]").strip() == "never fired"
        with urllib.request.urlopen(service["base"] + f"/api/v1/schedules/{schedule_id}", timeout=10) as r:
            stored = json.load(r)
        assert stored["sweep"]["method"] == "probe" and stored["timezone"] == "Europe/Berlin", stored

        page.uncheck(f"{row} [data-testid=schedule-enabled]")
        page.wait_for_function(
            f"""() => {{ const r = document.querySelector('{row}');
                        return r && r.dataset.enabled === 'false'; }}""",
            timeout=10_000,
        )
        assert page.inner_text(f"{row} [data-testid=schedule-next]").strip() == "—"
        page.click(f"{row} [data-testid=schedule-delete]")
        page.wait_for_selector(row, state="detached", timeout=10_000)
        assert not rec["pageerrors"], f"JavaScript errors: {rec['pageerrors']}"
        assert not rec["console"], f"console errors: {rec['console']}"
        page.screenshot(path=str(tmp_path / "schedules.png"), full_page=True)
    finally:
        context.close()


def _wait_api(service, path: str, done, timeout_s: float = 180.0) -> dict:
    return wait_until(
        lambda: done(body := _api(service, "GET", path)) and body, timeout_s, f"{path} finished", poll_s=0.5
    )


def test_live_status_shows_the_drive_running_during_a_run(service, browser, tmp_path):
    """During a run (grid method: the longest) the status is not frozen: the drive reads
    operation_enabled with its torque, fresh (not struck through), and the run's DAQ view fills."""
    context, page, rec = _open(browser, service["base"])
    job = None
    try:
        page.wait_for_function(
            """() => document.querySelector('[data-testid="live-mode"]').dataset.mode === 'live'""", timeout=15_000
        )
        job = _api(service, "POST", "/identifications", {"operating_point": OP1, "method": "grid"})
        try:
            page.wait_for_function(
                """() => {
                    const t = (id) => document.querySelector(`[data-testid="${id}"]`);
                    return t('bench-busy').textContent === 'busy'
                        && t('drive-state').textContent === 'operation_enabled' && !t('drive-state').dataset.stale
                        && Math.abs(parseFloat(t('drive-torque').textContent)) > 1 && !t('drive-torque').dataset.stale
                        && /^\\d/.test(t('run-speed').textContent) && /^\\d/.test(t('run-accel').textContent);
                }""",
                timeout=120_000,
            )
        except Exception:
            page.screenshot(path=str(tmp_path / "live_failure.png"), full_page=True)
            raise AssertionError(
                "the running drive never showed in the live status: %s\nservice log:\n%s"
                % (page.inner_text("#bench"), _log_tail(service["log"]))
            )
        torque = float(page.text_content('[data-testid="drive-torque"]'))
        assert 2.0 < torque < 3.0, torque  # 2.5 Nm commanded
        assert "s ago" in page.text_content('[data-testid="drive-torque-age"]')
        # acceleration in rad/s^2 beside its fraction of full scale (the setting comes with the status)
        fs = float(page.text_content('[data-testid="accel-fs"]'))
        a_fs = float(page.text_content('[data-testid="run-accel-fs"]'))
        a = float(page.text_content('[data-testid="run-accel"]'))
        assert abs(a - a_fs * fs) <= 0.01 * abs(a) + 1e-3, (a, a_fs, fs)
        page.screenshot(path=str(tmp_path / "live_run.png"), full_page=True)
        assert not rec["pageerrors"], rec["pageerrors"]
        assert not rec["console"], rec["console"]
    finally:
        if job is not None:  # the next tests get an idle bench
            _wait_api(service, f"/jobs/{job['id']}", lambda j: j["state"] in ("done", "failed", "cancelled"))
        context.close()


def test_docs_render_offline(service, browser):
    """/docs with every non-loopback request blocked: Swagger UI (served by the service) shows the operations."""
    base = service["base"]
    context = browser.new_context(viewport={"width": 1400, "height": 1000})
    blocked = []

    def only_loopback(route):
        url = route.request.url
        if url.startswith(("http://127.0.0.1:", "data:", "blob:")):
            route.continue_()
        else:
            blocked.append(url)
            route.abort()

    context.route("**/*", only_loopback)
    page = context.new_page()
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.goto(base + "/docs", wait_until="load")
        page.wait_for_function("() => document.querySelectorAll('.opblock').length >= 10", timeout=30_000)
        text = page.inner_text("body")
        assert "/api/v1/identifications" in text and "/api/v1/bench/status" in text
        assert not blocked, f"/docs asked the network: {blocked}"
        assert not errors, errors
        # no ReDoc: its page loads a logo from a CDN
        assert page.goto(base + "/redoc").status == 404
    finally:
        context.close()


def test_sweep_view_lists_non_ok_points_and_fits_1400_px(service, browser, tmp_path):
    """A sweep whose target cannot be met (80 dB, beyond the sensor's noise floor): while it runs the
    page is no wider than a 1400 px window (pause/cancel and the created column stay inside the card)
    and pause says "pausing..."; its non-ok points are listed with their reasons."""
    context = browser.new_context(viewport={"width": 1400, "height": 900})
    page = context.new_page()
    pageerrors = []
    page.on("pageerror", lambda e: pageerrors.append(str(e)))
    sweep = None
    try:
        page.goto(service["base"] + "/", wait_until="load")
        page.wait_for_function(
            """() => document.querySelector('[data-testid="live-mode"]').dataset.mode === 'live'""", timeout=15_000
        )
        page.fill('[data-testid="token"]', service["token"])
        # six points of about a second each: the pause below lands before the last one (and if it
        # does not, the sweep ends done: a pause asked during the last point has nothing left to hold)
        sweep = _api(
            service,
            "POST",
            "/sweeps",
            {
                # 2200 rpm: 4 Nm at 2500 rpm is outside the envelope of the motor settings (422)
                "grid": {"torque_nm": [1.0, 2.5, 4.0], "speed_rpm": [2000, 2200], "udc_v": [12]},
                "method": "probe",
                "options": {"target_db": 80},
            },
        )
        row = f'[data-testid="sweep-row"][data-sweep-id="{sweep["id"]}"]'
        page.wait_for_selector(f'{row} [data-action="pause"]', timeout=60_000)
        widths = page.evaluate("() => [document.documentElement.scrollWidth, window.innerWidth]")
        page.screenshot(path=str(tmp_path / "sweep_running_1400.png"), full_page=True)
        assert widths[0] <= widths[1], f"page {widths[0]} px wide in a {widths[1]} px window"
        # the row is running: pause answers with "pausing..." at once, resume follows once paused
        if page.get_attribute(row, "data-state") == "running":
            page.click(f'{row} [data-action="pause"]')
            page.wait_for_selector(f'{row} [data-testid="sweep-pausing"], {row}[data-state="paused"]', timeout=10_000)
            page.wait_for_selector(
                ", ".join(f'{row}[data-state="{state}"]' for state in ("paused", "done", "failed")), timeout=120_000
            )
            if page.get_attribute(row, "data-state") == "paused":
                page.click(f'{row} [data-action="resume"]')
        page.wait_for_function(
            f"""() => {{
                const r = document.querySelector('{row}');
                return r && ['done', 'failed', 'cancelled'].includes(r.dataset.state);
            }}""",
            timeout=SWEEP_TIMEOUT_MS * 2,
        )
        final = _api(service, "GET", f"/sweeps/{sweep['id']}")
        not_ok = [p for p in final["points"] if p["state"] != "ok"]
        assert not_ok, f"every point met 80 dB?: {final['progress']}"
        # the list follows the sweep's counts (fetched again when they change)
        try:
            page.wait_for_function(
                f"""(n) => document.querySelectorAll('{row} [data-testid="sweep-attention-point"]').length === n""",
                arg=len(not_ok),
                timeout=15_000,
            )
        except Exception:
            raise AssertionError(f"{len(not_ok)} non-ok points not listed: {page.inner_text(row)}")
        page.click(f'{row} [data-testid="sweep-attention"] summary')
        page.wait_for_selector(f'{row} [data-testid="sweep-attention"][open]', timeout=5_000)
        items = page.locator(f'{row} [data-testid="sweep-attention-point"]')
        reason = not_ok[0]["error"] or not_ok[0]["result"]["message"]
        # the sweep's second pass replaces a point's result without changing the counts: the list is
        # fetched again when the sweep's plant time changes, so wait for the final one
        try:
            page.wait_for_function(
                f"""(needle) => {{
                    const p = document.querySelector('{row} [data-testid="sweep-attention-point"]');
                    return p && p.textContent.includes(needle);
                }}""",
                arg=reason[:20],
                timeout=15_000,
            )
        except Exception:
            pass  # the assertion below says what was shown instead
        first = items.first.text_content()
        assert not_ok[0]["state"] in first and reason and reason[:20] in first, (first, not_ok[0])
        assert "elapsed" in page.inner_text(f'{row} [data-testid="sweep-timing"]')
        widths = page.evaluate("() => [document.documentElement.scrollWidth, window.innerWidth]")
        assert widths[0] <= widths[1], f"page {widths[0]} px wide in a {widths[1]} px window"
        page.screenshot(path=str(tmp_path / "sweep_attention_1400.png"), full_page=True)
        assert not pageerrors, pageerrors
    finally:
        if sweep is not None:
            _wait_api(
                service, f"/sweeps/{sweep['id']}", lambda s: s["state"] not in ("queued", "running"), timeout_s=300
            )
        context.close()


def test_map_download_button_shows_the_crc_and_the_bench_shows_the_map_the_drive_holds(service, browser, tmp_path):
    """Map panel, "Download to drive" (operator token): a complete map answers with the CRC the drive
    read back and the Bench panel shows that map id and CRC; a map with no ok cell is refused with the
    service's message and no way around; a partial map goes with its fill, and without the fill it is
    refused until "download anyway" (force)."""
    from drivers.lut_image import crc_hex, image_crc
    from service.api.public.maps import map_public
    from service.maps.lut_export import lut_image
    from service.store.storage import Storage
    from tests.support.stored_maps import CELLS, stored_map

    storage = Storage(service["log"].parent / "ripplecal.db")  # the service's own database (WAL)
    full, empty, partial = (
        stored_map(storage),
        stored_map(storage, failing=set(CELLS)),
        stored_map(storage, failing={CELLS[2]}),
    )
    crc = {i: crc_hex(image_crc(lut_image(map_public(storage, i).model_dump()))) for i in (full, partial)}
    context, page, rec = _open(browser, service["base"])
    msg = '[data-testid="map-download-msg"]'

    def select(map_id: int) -> None:
        page.select_option('[data-testid="map-select"]', str(map_id))
        page.wait_for_selector(f'[data-testid="map-download"][data-map-id="{map_id}"]:not([disabled])', timeout=10_000)

    def click(button: str, outcome: str) -> str:
        page.click(f'[data-testid="{button}"]')
        page.wait_for_selector(f'{msg}[data-outcome="{outcome}"]', timeout=30_000)
        return page.inner_text(msg)

    def download(map_id: int, outcome: str) -> str:
        select(map_id)
        return click("map-download", outcome)

    try:
        page.wait_for_function(
            """() => document.querySelector('[data-testid="live-mode"]').dataset.mode === 'live'""", timeout=15_000
        )
        page.fill('[data-testid="token"]', service["token"])
        # the newest map is shown first; then each is picked by hand
        page.wait_for_selector(f'[data-testid="map-download"][data-map-id="{partial}"]', timeout=15_000)
        text = download(full, "ok")
        assert f"Map {full} is in the drive: CRC-32 {crc[full]} read back" in text and "4 of 4 cells ok" in text, text
        page.wait_for_function(
            f"""() => document.querySelector('[data-testid="drive-lut"]').textContent
                                   === 'map {full} · {crc[full]}'""",
            timeout=15_000,
        )

        text = download(empty, "refused")
        assert f"Map {empty} not downloaded" in text and "no valid cell (0 of 4 ok)" in text, text
        assert page.locator('[data-testid="map-download-force"]').count() == 0

        # the partial map's failed cell carries a fill: with fill (the default) no hole, without it refused
        text = download(partial, "ok")
        assert f"CRC-32 {crc[partial]}" in text and "3 of 4 cells ok" in text and "1 filled" in text, text
        page.uncheck('[data-testid="map-download-fill"]')
        text = click("map-download", "refused")
        assert "1 of 4 cells are not ok" in text, text
        text = click("map-download-force", "ok")
        assert "3 of 4 cells ok" in text and "forced" in text, text
        page.check('[data-testid="map-download-fill"]')
        text = download(partial, "ok")
        page.wait_for_function(
            f"""() => document.querySelector('[data-testid="drive-lut"]').textContent
                                   === 'map {partial} · {crc[partial]}'""",
            timeout=15_000,
        )
        page.screenshot(path=str(tmp_path / "map_download.png"), full_page=True)
        assert not rec["pageerrors"], rec["pageerrors"]
        # the refused POSTs are the only console errors (Chromium logs every failed fetch)
        assert all("409" in m or "422" in m for m in rec["console"]), rec["console"]
    finally:
        context.close()


def test_a_map_of_two_orders_shows_a_heat_map_per_order(service, browser, tmp_path):
    """Map panel, a map of orders 6 and 12 (issue 28): the order picker appears, the meta line names both orders
    and the 12th's counts, and picking the 12th draws that order's cells (its gamma, its title)."""
    from service.store.storage import Storage
    from tests.support.stored_maps import stored_two_order_map

    storage = Storage(service["log"].parent / "ripplecal.db")  # the service's own database (WAL)
    map_id = stored_two_order_map(storage)
    context, page, rec = _open(browser, service["base"])
    try:
        page.wait_for_selector('[data-testid="map-select"] option', state="attached", timeout=15_000)
        page.select_option('[data-testid="map-select"]', str(map_id))
        page.wait_for_function(
            """() => document.querySelector('[data-testid="map-meta"]').textContent.includes('h = 6 + 12')""",
            timeout=15_000,
        )
        assert page.is_visible('[data-testid="order-select"]')
        meta = page.inner_text('[data-testid="map-meta"]')
        assert "order 12: 3 ok of 4, 1 filled" in meta, meta

        def gammas() -> list:
            return page.evaluate(
                "() => document.getElementById('plot-gamma').data[0].z.flat().filter((v) => v !== null)"
            )

        page.wait_for_function("() => (document.getElementById('plot-gamma').data || []).length > 0", timeout=15_000)
        assert sorted(round(v, 3) for v in gammas()) == [1.0, 2.0, 3.0, 4.0]
        page.select_option('[data-testid="order-select"]', "12")
        page.wait_for_function(
            """() => document.getElementById('plot-gamma').layout.title.text.startsWith('order 12')""", timeout=15_000
        )
        assert sorted(round(v, 3) for v in gammas()) == [0.5, 1.0, 1.5, 2.0]  # the fill shown as the others
        page.screenshot(path=str(tmp_path / "two_orders.png"), full_page=True)
        assert not rec["pageerrors"], rec["pageerrors"]
    finally:
        context.close()


def test_map_compare_view_and_the_outliers_of_the_map_view(service, browser, tmp_path):
    """Two maps put into the service's database from stored results (no sweep: tests/support/maps.py):
    the Map panel rings map a's planted outlier and gives its reason; the Compare panel, with map b
    picked, shows |delta theta| and the predicted suppression of every cell, the outlier the worst."""
    from service.store.storage import Storage
    from tests.support.maps import make_map, theta_of

    grid = {"torque_nm": [1.0, 2.5, 4.0], "speed_rpm": [1000.0, 2000.0, 3000.0], "udc_v": [12.0]}
    outlier = (2.5, 2000.0, 12.0)

    def smooth(p):
        return theta_of(2.0 + 0.2 * p[0], 270.0 + p[1] / 200.0)

    storage = Storage(service["log"].parent / "ripplecal.db")  # the service's own database
    map_a = make_map(storage, grid, lambda p: theta_of(6.0, 200.0) if p == outlier else smooth(p))
    map_b = make_map(storage, grid, smooth)
    context, page, rec = _open(browser, service["base"])
    try:
        page.wait_for_function(
            f"""() => [...document.querySelectorAll('[data-testid="map-select"] option')]
                                          .some((o) => o.value === '{map_a}')""",
            timeout=15_000,
        )
        page.select_option('[data-testid="map-select"]', str(map_a))
        quality = page.locator('[data-testid="map-quality"]')
        quality.wait_for(state="visible", timeout=10_000)
        assert "T* 2.5 N·m, n 2000 rpm" in quality.inner_text()
        assert "from the median of its 4 ok neighbours" in quality.inner_text()
        assert "1 outlier(s)" in page.inner_text('[data-testid="map-meta"]')
        page.wait_for_function(
            """() => { const d = document.querySelector('[data-testid="plot-gamma"]');
                                          return d.data && d.data.some((t) => t.name === 'outlier'); }""",
            timeout=10_000,
        )
        assert page.inner_text('[data-testid="compare-a"]') == f"a: map {map_a}"

        page.select_option('[data-testid="compare-b"]', str(map_b))
        rows = page.locator('[data-testid="compare-row"][data-compared="1"]')
        page.wait_for_function(
            """() => document.querySelectorAll('[data-testid="compare-row"]').length === 9""", timeout=10_000
        )
        assert rows.count() == 9
        assert "9 cells compared" in page.inner_text('[data-testid="compare-summary"]')
        assert "at 2.5 N·m / 2000 rpm" in page.inner_text('[data-testid="compare-summary"]')
        page.wait_for_function(
            """() => ['plot-compare-theta', 'plot-compare-supp'].every((id) =>
                                          document.getElementById(id).classList.contains('js-plotly-plot'))""",
            timeout=10_000,
        )
        moved = [r for r in rows.all_inner_texts() if r.startswith("2.5\t2000")]
        assert len(moved) == 1 and float(moved[0].split("\t")[5]) > 1.0, moved
        page.screenshot(path=str(tmp_path / "map_compare.png"), full_page=True)
        assert not rec["pageerrors"], f"JavaScript errors: {rec['pageerrors']}"
        assert not rec["console"], f"console errors: {rec['console']}"
    finally:
        context.close()


def test_validate_on_drive_draws_the_suppression_over_grid_points_and_midpoints(service, browser, tmp_path):
    """A 2 x 1 map (made through the API): "Validate on drive" starts the job; when it ends the panel
    draws the suppression measured in the drive's LUT mode over the finer grid (3 torques x 1 speed:
    2 grid points marked, 1 midpoint) with the summary line."""
    sweep = _api(
        service,
        "POST",
        "/sweeps",
        {"grid": {"torque_nm": [2.0, 3.0], "speed_rpm": [1500], "udc_v": [12]}, "method": "probe"},
    )
    sweep = _wait_api(service, f"/sweeps/{sweep['id']}", lambda s: s["state"] not in ("queued", "running", "paused"))
    assert sweep["state"] == "done" and sweep["map_id"] is not None, sweep
    map_id = sweep["map_id"]
    context, page, rec = _open(browser, service["base"])
    try:
        page.wait_for_function(
            """() => document.querySelector('[data-testid="live-mode"]').dataset.mode === 'live'""", timeout=15_000
        )
        page.select_option('[data-testid="map-select"]', str(map_id))
        page.wait_for_function(
            """() => /Not validated/.test(document.querySelector('[data-testid="validation-meta"]').textContent)""",
            timeout=10_000,
        )
        # without a token the refusal is shown, nothing runs
        page.fill('[data-testid="token"]', "")
        page.click('[data-testid="validate-btn"]')
        page.wait_for_function(
            """() => !document.querySelector('[data-testid="validation-note"]').hidden
                && /refused/i.test(document.querySelector('[data-testid="validation-note"]').textContent)""",
            timeout=10_000,
        )
        page.fill('[data-testid="token"]', service["token"])
        page.check('[data-testid="validate-force"]')  # whatever the sweep reached, validate it
        page.click('[data-testid="validate-btn"]')
        try:
            page.wait_for_function(
                """() => document.querySelector('[data-testid="map-validation"]').dataset.validated === '1'
                    && document.querySelector('[data-testid="plot-validation"]').classList.contains('js-plotly-plot')""",
                timeout=SWEEP_TIMEOUT_MS,
            )
        except Exception:
            page.screenshot(path=str(tmp_path / "validation_failure.png"), full_page=True)
            raise AssertionError(
                "validation not drawn: note=%r meta=%r\nservice log:\n%s"
                % (
                    page.text_content('[data-testid="validation-note"]'),
                    page.text_content('[data-testid="validation-meta"]'),
                    _log_tail(service["log"]),
                )
            )
        v = _api(service, "GET", f"/maps/{map_id}/validation")
        meta = page.inner_text('[data-testid="validation-meta"]')
        assert f"job {v['job_id']}" in meta and "grid" in meta and "midpoints" in meta, meta
        drawn = page.evaluate("""() => {
            const d = document.getElementById('plot-validation').data;
            return {x: d[0].x, y: d[0].y, z: d[0].z, gridX: d[1].x, text: d[0].text};
        }""")
        assert drawn["x"] == [2.0, 2.5, 3.0] and drawn["y"] == [1500.0]
        assert drawn["gridX"] == [2.0, 3.0]  # the grid points are marked, the midpoint is not
        measured = {c["operating_point"]["torque_nm"]: c["suppression_db"] for c in v["cells"]}
        for j, t in enumerate(drawn["x"]):
            if measured[t] is None:
                assert drawn["z"][0][j] is None
            else:
                assert drawn["z"][0][j] == pytest.approx(measured[t])
        assert "midpoint (interpolated)" in drawn["text"][0][1] and "grid point" in drawn["text"][0][0]
        assert not rec["pageerrors"], f"JavaScript errors: {rec['pageerrors']}"
        assert not [c for c in rec["console"] if "401" not in c], f"console errors: {rec['console']}"
        page.screenshot(path=str(tmp_path / "map_validation.png"), full_page=True)
    finally:
        context.close()


def test_sweep_preview_shows_the_onset_per_torque_and_the_speeds_placed_around_it(service, browser, tmp_path):
    """The Sweeps form's Preview (POST /sweeps/preview: no token, nothing queued). With "speeds around FW
    onset" ticked, 1..4 N·m x 1000..2600 rpm at 12 V on paper-bench's nominal motor: the predicted onsets
    2159, 2065, 1965, 1862 rpm, the six speeds placed at and 100 rpm around them marked on the speed
    axis, 44 points and the bench-time estimate; unticked, the grid stays 20 points, onsets still shown."""
    sweeps_before = {s["id"] for s in _api(service, "GET", "/sweeps")}
    context, page, rec = _open(browser, service["base"])
    try:
        page.fill('[data-testid="token"]', "")  # the preview needs no token
        page.fill('[data-testid="sweep-torque"]', "1, 2, 3, 4")
        page.fill('[data-testid="sweep-speed"]', "1000, 1400, 1800, 2200, 2600")
        page.fill('[data-testid="sweep-udc"]', "12")
        page.select_option('[data-testid="sweep-method"]', "probe")
        page.check('[data-testid="sweep-regime"]')
        page.fill('[data-testid="sweep-spacing"]', "100")
        page.click('[data-testid="sweep-preview-btn"]')
        box = page.locator('[data-testid="sweep-preview"]')
        try:
            box.wait_for(state="visible", timeout=10_000)
        except Exception:
            page.screenshot(path=str(tmp_path / "sweep_preview_failure.png"), full_page=True)
            raise AssertionError(
                "no preview shown: error=%r\nconsole: %s"
                % (page.inner_text('[data-testid="sweep-error"]'), rec["console"] + rec["pageerrors"])
            )
        onsets = page.eval_on_selector_all(
            '[data-testid="sweep-preview-onset"]', "els => els.map((e) => e.textContent)"
        )
        assert onsets == ["1 N·m: 2159 rpm", "2 N·m: 2065 rpm", "3 N·m: 1965 rpm", "4 N·m: 1862 rpm"], onsets
        added = page.eval_on_selector_all(
            '[data-testid="sweep-preview-speed"][data-added="1"]',
            "els => els.map((e) => [e.dataset.speed, e.tagName, e.title])",
        )
        assert [a[0] for a in added] == ["1760", "1860", "1960", "2060", "2160", "2260"], added
        assert all(tag == "STRONG" and "field-weakening onset" in why for _, tag, why in added), added
        kept = page.eval_on_selector_all(
            '[data-testid="sweep-preview-speed"][data-added="0"]', "els => els.map((e) => e.dataset.speed)"
        )
        assert kept == ["1000", "1400", "1800", "2200", "2600"], kept
        summary = page.inner_text('[data-testid="sweep-preview-summary"]')
        assert (
            summary.startswith("44 operating points (20 requested; 6 speed values added") and "would queue" in summary
        )
        estimate = page.inner_text('[data-testid="sweep-preview-estimate"]')
        # 4 N·m at 2600 rpm is beyond what the motor settings hold at 12 V: listed, not run, not in the estimate
        assert "Estimated bench time ≈ 37 s" in estimate and "estimate at speedup 1" in estimate, estimate
        not_run = page.inner_text('[data-testid="sweep-preview-not-run"]')
        assert not_run.startswith("1 point outside the envelope of the motor settings, not run: 4 N·m @ 2600 rpm"), (
            not_run
        )
        assert page.inner_text('[data-testid="sweep-preview-margin"]') == "0.95"
        page.screenshot(path=str(tmp_path / "sweep_preview.png"), full_page=True)

        # unticked: the grid as entered, the onsets still predicted
        page.uncheck('[data-testid="sweep-regime"]')
        assert box.get_attribute("data-stale") == "1"  # the shown plan is no longer the form's
        page.click('[data-testid="sweep-preview-btn"]')
        page.wait_for_function(
            """() => document.querySelector('[data-testid="sweep-preview-summary"]')
                                        .textContent.startsWith('20 operating points')""",
            timeout=10_000,
        )
        assert page.locator('[data-testid="sweep-preview-speed"][data-added="1"]').count() == 0
        assert page.locator('[data-testid="sweep-preview-onset"]').count() == 4
        assert box.get_attribute("data-stale") is None
        # nothing was queued, no error shown or thrown
        assert {s["id"] for s in _api(service, "GET", "/sweeps")} == sweeps_before
        assert page.is_hidden('[data-testid="sweep-error"]')
        assert not rec["pageerrors"], f"JavaScript errors: {rec['pageerrors']}"
        assert not rec["console"], f"console errors: {rec['console']}"
    finally:
        context.close()


def test_refine_on_drive_shows_its_rounds_and_the_refined_validation_beside_the_source(service, browser, tmp_path):
    """A 2 x 2 probe map (made through the API), refined from the map panel ("Refine on drive", target
    30 dB, at most 4 cells): the progress shows a round and a phase while it runs; at the end the outcome
    names whether the map holds or why it stopped, the rounds table has a row per round, and the source's
    validation and the refined map's are drawn side by side (numeric axes, the refined one titled with the
    refined map's id, as GET /jobs/{id} names it)."""
    sweep = _api(
        service,
        "POST",
        "/sweeps",
        {"grid": {"torque_nm": [2.0, 3.0], "speed_rpm": [1200, 2200], "udc_v": [12]}, "method": "probe"},
    )
    sweep = _wait_api(service, f"/sweeps/{sweep['id']}", lambda s: s["state"] not in ("queued", "running", "paused"))
    assert sweep["state"] == "done" and sweep["map_id"] is not None, sweep
    map_id = sweep["map_id"]
    context, page, rec = _open(browser, service["base"])
    progress = '[data-testid="refine-progress"]'
    try:
        page.wait_for_function(
            """() => document.querySelector('[data-testid="live-mode"]').dataset.mode === 'live'""", timeout=15_000
        )
        page.fill('[data-testid="token"]', service["token"])
        page.wait_for_function(
            f"""() => [...document.querySelectorAll('[data-testid="map-select"] option')]
                                          .some((o) => o.value === '{map_id}')""",
            timeout=15_000,
        )
        page.select_option('[data-testid="map-select"]', str(map_id))
        page.wait_for_selector('[data-testid="refine-button"]:not([disabled])', timeout=10_000)
        page.fill('[data-testid="refine-max-cells"]', "4")
        page.fill('[data-testid="refine-target"]', "30")
        page.select_option('[data-testid="refine-lut-cells"]', "int11")  # 3 bytes a cell (LUT image version 6)
        # every (phase, round) the progress line shows, recorded as it changes
        page.evaluate(f"""() => {{
            const p = document.querySelector('{progress}');
            window.refineSeen = [];
            new MutationObserver(() => window.refineSeen.push([p.dataset.phase, p.dataset.round, p.textContent]))
                .observe(p, {{attributes: true, childList: true, characterData: true, subtree: true}});
        }}""")
        with page.expect_response(lambda r: r.url.endswith(f"/api/v1/maps/{map_id}/refine")) as answer:
            page.click('[data-testid="refine-button"]')
        assert answer.value.status == 202, answer.value.text()
        sent = answer.value.request.post_data_json
        assert (sent["lut_cells"], sent["max_bytes"], sent["max_cells"], "validation" in sent) == (
            "int11",
            2048,
            4,
            False,
        )
        job_id = answer.value.json()["id"]
        try:
            page.wait_for_selector('[data-testid="refine-outcome"]:not([hidden])', timeout=180_000)
        except Exception:
            page.screenshot(path=str(tmp_path / "refine_failure.png"), full_page=True)
            raise AssertionError(
                "no outcome: progress=%r note=%r\nservice log:\n%s"
                % (
                    page.text_content(progress),
                    page.text_content('[data-testid="refine-note"]'),
                    _log_tail(service["log"]),
                )
            )
        job = _api(service, "GET", f"/jobs/{job_id}")
        result = job["result"]
        assert job["kind"] == "refinement" and job["state"] == "done", job
        refined = result["map_id"]
        assert result["rounds"] and result["rounds"][-1]["map_id"] == refined, result
        assert _api(service, "GET", f"/maps/{refined}")["provenance"]["lut_cells"] == "int11"

        seen = page.evaluate("() => window.refineSeen")
        running = [s for s in seen if s[0] in ("measure", "validate") and s[1].isdigit()]
        assert running, seen
        assert any(s[0] == "validate" and "validating map" in s[2] for s in running), seen
        assert all(f"of max {result['max_cells']} cells identified" in s[2] for s in running), seen

        outcome = page.locator('[data-testid="refine-outcome"]')
        text = outcome.inner_text()
        if result["holds"]:
            assert outcome.get_attribute("data-holds") == "1" and text.startswith("Holds"), text
        else:
            assert outcome.get_attribute("data-holds") == "0" and result["stopped"] in text, (text, result["stopped"])
        assert outcome.get_attribute("data-state") == "done"
        rows = page.eval_on_selector_all('[data-testid="refine-round"]', "els => els.map((e) => e.dataset.mapId)")
        assert rows == [str(r["map_id"]) for r in result["rounds"]] and len(rows) >= 1, rows
        # listed as what it is (issue 30): the sweeps' row names the map it refines, the map note the refinement
        sweep_row = f'[data-testid="sweep-row"][data-sweep-id="{result["refinement_id"]}"]'
        page.wait_for_selector(f'{sweep_row}[data-state="done"]', timeout=15_000)
        assert page.get_attribute(f"{sweep_row} [data-testid=sweep-kind]", "data-kind") == "refinement"
        assert f"refinement of map {map_id}" in page.inner_text(f"{sweep_row} [data-testid=sweep-kind]")
        bar = page.inner_text(f"{sweep_row} [data-testid=sweep-progress]")
        done, total = re.match(r"(\d+) / (\d+) cells", bar).groups()
        assert done == total, bar
        page.wait_for_function(  # set once the map list is reloaded after the event: waited for
            f"""() => document.querySelector('[data-testid="map-note"]').textContent
                .includes('Refinement {result["refinement_id"]} finished — showing its refined map')""",
            timeout=15_000,
        )

        page.wait_for_function(
            f"""() => {{
            const s = document.querySelector('[data-testid="validation-heatmap-source"]');
            const r = document.querySelector('[data-testid="validation-heatmap-refined"]');
            return s.classList.contains('js-plotly-plot') && r.classList.contains('js-plotly-plot')
                && r.dataset.mapId === '{refined}';
        }}""",
            timeout=15_000,
        )
        drawn = page.evaluate("""() => ['validation-heatmap-source', 'validation-heatmap-refined'].map((t) => {
            const d = document.querySelector(`[data-testid="${t}"]`);
            return {title: d.layout.title.text, xtype: d.layout.xaxis.type, ytype: d.layout.yaxis.type,
                    y: d.data[0].y, zmin: d.data[0].zmin, zmax: d.data[0].zmax};
        })""")
        source, after = drawn
        assert f"refined map {refined}" in after["title"] and "points" in after["title"], after["title"]
        assert f"map {map_id}" in source["title"] and "points" in source["title"], source["title"]
        assert {source["xtype"], source["ytype"], after["xtype"], after["ytype"]} == {"linear"}
        assert (source["zmin"], source["zmax"]) == (after["zmin"], after["zmax"])  # one colour scale
        for r in result["rounds"][:-1]:  # what the rounds inserted sits on the refined map's axes
            for v in r["inserted"].get("speed_rpm", []):
                assert v in after["y"], (v, after["y"])
        # the refined map opens in the map view; its option and summary line say where it comes from
        page.click('[data-testid="refine-open-map"]')
        page.wait_for_function(
            f"""() => document.querySelector('[data-testid="map-select"]').value === '{refined}'
            && document.querySelector('[data-testid="map-meta"]').dataset.refinedFrom === '{map_id}'""",
            timeout=15_000,
        )
        assert f"refined from {map_id}" in page.inner_text('[data-testid="map-meta"]')
        option = page.inner_text(f'[data-testid="map-select"] option[value="{refined}"]')
        assert f"refined from {map_id}" in option, option
        page.screenshot(path=str(tmp_path / "map_refine.png"), full_page=True)
        assert not rec["pageerrors"], f"JavaScript errors: {rec['pageerrors']}"
        assert not rec["console"], f"console errors: {rec['console']}"
    finally:
        context.close()


def test_lab_overview_lists_every_bench_and_the_picker_sends_a_sweep_to_another_bench(service, browser, tmp_path):
    """The lab panel shows this service's bench online and a bench only named by a queued job as never
    seen, with its queue; the top bar's picker (default: this bench) sends the sweep form's run to the
    bench chosen, where it waits, and the sweep's row says for what."""
    job = _api(service, "POST", "/identifications", {"operating_point": OP1, "bench": "bench-b"})
    assert job["state"] == "queued" and job["bench"] == "bench-b"
    context, page, rec = _open(browser, service["base"])
    sweep_id = None
    try:
        page.fill('[data-testid="token"]', service["token"])
        own = page.locator('[data-testid="lab-row"][data-bench="emulated"]')
        own.wait_for(timeout=15_000)
        assert own.get_attribute("data-online") == "true"
        assert own.locator('[data-testid="lab-online"]').inner_text() == "online"
        other = page.locator('[data-testid="lab-row"][data-bench="bench-b"]')
        other.wait_for(timeout=15_000)
        assert other.get_attribute("data-online") == "false"
        assert "never seen" in other.locator('[data-testid="lab-online"]').inner_text()
        assert other.locator('[data-testid="lab-queue"]').inner_text() == "1"
        # the picker: this service's bench by default, the others to choose
        assert page.input_value('[data-testid="bench-pick"]') == "emulated"
        options = page.eval_on_selector_all('[data-testid="bench-pick"] option', "os => os.map((o) => o.value)")
        assert options == ["bench-b", "emulated"], options
        page.select_option('[data-testid="bench-pick"]', "bench-b")
        page.fill('[data-testid="sweep-torque"]', "1, 2")
        page.fill('[data-testid="sweep-speed"]', "1000")
        page.fill('[data-testid="sweep-udc"]', "12")
        page.click('[data-testid="sweep-submit"]')
        ok = page.locator('[data-testid="sweep-ok"]')
        ok.wait_for(state="visible", timeout=10_000)
        assert "waits for bench bench-b (never seen" in ok.inner_text(), ok.inner_text()
        sweep = _api(service, "GET", "/sweeps?limit=1")[0]
        sweep_id = sweep["id"]
        assert sweep["bench"] == "bench-b" and sweep["state"] == "queued", sweep
        page.wait_for_function(
            """() => document.querySelector('[data-testid="lab-row"][data-bench="bench-b"] [data-testid="lab-queue"]')
                .innerText === '2'""",
            timeout=10_000,
        )
        note = page.locator('[data-testid="sweep-waiting-for"]').first
        note.wait_for(timeout=10_000)
        assert "bench bench-b" in note.inner_text()
        page.screenshot(path=str(tmp_path / "lab.png"), full_page=True)
        assert not rec["pageerrors"], f"JavaScript errors: {rec['pageerrors']}"
        assert not rec["console"], f"console errors: {rec['console']}"
    finally:
        context.close()
        # what waits for a bench no service serves is cancelled from here (no service has taken it)
        _api(service, "POST", f"/jobs/{job['id']}/cancel")
        if sweep_id is not None:
            assert _api(service, "POST", f"/sweeps/{sweep_id}/cancel")["state"] == "cancelled"


def test_runup_panel_draws_the_campbell_diagram_and_the_order_cut_before_and_after(service, browser, tmp_path):
    """A run-up started from the panel (injection off: before) is drawn as its Campbell diagram (order x speed,
    colour = dB FS); a second one at the same torque and U_dc with a fixed theta (after, through the API) is
    paired with it on the order cut: both curves of the calibrated order with their noise floors."""
    context, page, rec = _open(browser, service["base"])
    try:
        page.wait_for_function(
            """() => document.querySelector('[data-testid="live-mode"]').dataset.mode === 'live'""", timeout=15_000
        )
        page.fill('[data-testid="token"]', service["token"])
        for field, value in (("from", "1200"), ("to", "1500"), ("rate", "100"), ("orders", "6, 12")):
            page.fill(f'[data-testid="runup-{field}"]', value)
        page.click('[data-testid="runup-submit"]')
        page.wait_for_function(
            """() => document.querySelector('[data-testid="runups"]').dataset.drawn === '1'""",
            timeout=SWEEP_TIMEOUT_MS,
        )
        campbell = page.evaluate("""() => {
            const d = document.getElementById('plot-campbell').data[0];
            return {type: d.type, y: d.y, bins: d.x.length, rows: d.z.length, cols: d.z[0].length};
        }""")
        assert campbell["type"] == "heatmap" and campbell["y"] == [6, 12] and campbell["rows"] == 2
        assert campbell["bins"] == campbell["cols"] and campbell["bins"] >= 30  # 300 rpm in bins of 10 rpm
        meta = page.inner_text('[data-testid="runup-meta"]')  # the orders to pick from, largest first
        assert "orders 20 dB above the floor: " in meta and "6" in meta.split("floor: ")[1], meta
        before = _api(service, "GET", "/runups?limit=1")[0]
        assert before["request"]["injection"] == "off" and before["state"] == "done", before
        after = _api(
            service,
            "POST",
            "/runups",
            {
                "torque_nm": 2.5,
                "udc_v": 12,
                "speed_rpm": [1200, 1500],
                "injection": "theta",
                "theta": {"theta_cos": 0.02, "theta_sin": -0.03},
                "orders": [6, 12],
            },
        )
        _wait_api(service, f"/runups/{after['id']}", lambda j: j["state"] not in ("queued", "running"))
        page.select_option('[data-testid="runup-select"]', str(after["id"]))
        page.wait_for_function(
            """() => document.querySelector('[data-testid="runups"]').dataset.drawn === '2'""", timeout=30_000
        )
        names = page.evaluate("() => document.getElementById('plot-order-cut').data.map((t) => t.name)")
        assert names[0].startswith("before (injection off") and names[2].startswith("after (injection theta"), names
        assert len(names) == 4 and "noise floor" in names[1] and "noise floor" in names[3], names
        # the cut of another order the run-ups tracked (a LUT of several orders: each of them)
        page.select_option('[data-testid="runup-cut-order"]', "12")
        page.wait_for_function(
            """() => document.getElementById('plot-order-cut').layout.yaxis.title.text === 'order 12 (dB FS)'""",
            timeout=15_000,
        )
        assert not rec["pageerrors"], f"JavaScript errors: {rec['pageerrors']}"
        page.screenshot(path=str(tmp_path / "runups.png"), full_page=True)
    finally:
        context.close()
