// ripplecal dashboard: bench status (SSE with polling fallback), sweeps, compensation maps,
// single identifications and the result view (paper Fig. 8, 9, 10).
// Plain JS, no build step. All API data is written with textContent (never innerHTML).
"use strict";

(function () {
  const API = "/api/v1";
  const TOKEN_KEY = "ripplecal.token";
  const POLL_MS = 2000;          // fallback poll period of /bench/status
  const SSE_STALE_MS = 3500;     // no bench.status over SSE for this long -> poll
  const SWEEP_POLL_MS = 5000;    // sweep list refresh while SSE is down

  const $ = (id) => document.getElementById(id);

  // ---------------------------------------------------------------- helpers
  function fmt(v, digits) {
    if (v === null || v === undefined || v === "") return "—";
    const x = Number(v);
    if (!Number.isFinite(x)) return String(v);
    return digits === undefined ? String(x) : x.toFixed(digits);
  }

  function fmtInt(v) {
    if (v === null || v === undefined) return "—";
    const x = Number(v);
    return Number.isFinite(x) ? x.toLocaleString("en-US") : String(v);
  }

  function setText(id, text, title) {
    const el = $(id);
    if (!el) return;
    if (el.textContent !== text) el.textContent = text;
    if (title !== undefined) el.title = title;
  }

  function setFlag(id, value, goodWhen, yes, no) {
    const el = $(id);
    if (value === null || value === undefined) {
      el.textContent = "—";
      el.dataset.level = "";
      return;
    }
    el.textContent = value ? (yes || "yes") : (no || "no");
    el.dataset.level = (Boolean(value) === goodWhen) ? "ok" : "bad";
  }

  // CiA 402 state -> colour class
  function stateLevel(state) {
    if (!state) return "";
    const s = String(state).toLowerCase();
    if (s === "operation_enabled") return "ok";
    if (s.includes("fault")) return "bad";
    if (s === "quick_stop_active") return "warn";
    return "idle";
  }

  function setState(id, state) {
    const el = $(id);
    el.textContent = state ? String(state) : "—";
    el.dataset.level = stateLevel(state);
  }

  function shortTime(iso) {
    if (!iso) return "—";
    const d = new Date(iso);
    if (isNaN(d)) return String(iso);
    const pad = (n) => String(n).padStart(2, "0");
    return `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ` +
      `${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}`;
  }

  function token() {
    return $("token").value.trim();
  }

  async function apiGet(path) {
    const r = await fetch(API + path, { headers: { Accept: "application/json" }, cache: "no-store" });
    if (!r.ok) throw await apiError(r);
    return r.json();
  }

  async function apiPost(path, body) {
    const headers = { Accept: "application/json" };
    if (body !== undefined) headers["Content-Type"] = "application/json";
    const t = token();
    if (t) headers.Authorization = "Bearer " + t;
    const r = await fetch(API + path, {
      method: "POST", headers, body: body === undefined ? undefined : JSON.stringify(body),
    });
    if (!r.ok) throw await apiError(r);
    return r.status === 204 ? null : r.json();
  }

  // Turn an error response into an Error whose .lines are human-readable messages.
  async function apiError(r) {
    let payload = null;
    try {
      payload = await r.json();
    } catch (_) { /* not JSON */ }
    const detail = payload && payload.detail !== undefined ? payload.detail : null;
    const lines = [];
    if (r.status === 401 || (r.status === 403 && detail === "Not authenticated")) {
      lines.push("token missing or invalid");
    } else if (r.status === 403) {
      lines.push("not allowed" + (detail ? ": " + detailText(detail) : " (operator role required)"));
    } else if (r.status === 422 && Array.isArray(detail)) {
      for (const d of detail) {
        const loc = Array.isArray(d.loc) ? d.loc.filter((p) => p !== "body").join(".") : String(d.loc || "");
        lines.push((loc ? loc + ": " : "") + (d.msg || JSON.stringify(d)));
      }
    } else if (detail !== null) {
      lines.push(detailText(detail));
    } else {
      lines.push(`HTTP ${r.status} ${r.statusText || ""}`.trim());
    }
    const err = new Error(lines.join("; "));
    err.status = r.status;
    err.lines = lines;
    err.detail = detail;
    return err;
  }

  function detailText(detail) {
    if (typeof detail === "string") return detail;
    if (Array.isArray(detail)) return detail.map((d) => (d && d.msg) || JSON.stringify(d)).join("; ");
    return JSON.stringify(detail);
  }

  function showMsg(id, lines, title) {
    const el = $(id);
    el.replaceChildren();
    if (!lines || lines.length === 0) {
      el.hidden = true;
      return;
    }
    if (title) {
      const b = document.createElement("strong");
      b.textContent = title;
      el.appendChild(b);
    }
    if (lines.length === 1 && !title) {
      el.textContent = lines[0];
    } else {
      const ul = document.createElement("ul");
      for (const l of lines) {
        const li = document.createElement("li");
        li.textContent = l;
        ul.appendChild(li);
      }
      el.appendChild(ul);
    }
    el.hidden = false;
  }

  // ---------------------------------------------------------------- (1) bench status
  let lastBenchAt = 0;        // Date.now() of the last bench.status from SSE
  let lastStatus = null;

  function renderStatus(s) {
    lastStatus = s;
    const drive = s.drive || {};
    const load = s.load || {};
    const daq = s.daq || {};
    setText("bench-name", s.bench || "—");
    setState("drive-state", drive.state);
    setText("drive-speed", fmt(drive.speed_rpm, 1));
    setText("drive-torque", fmt(drive.torque_nm, 3));
    setText("drive-udc", fmt(drive.udc_v, 2));
    setFlag("drive-heartbeat", drive.heartbeat_ok, true, "ok", "lost");
    setState("load-state", load.state);
    setText("load-speed", fmt(load.speed_rpm, 1));
    setText("daq-frames", fmtInt(daq.frames));
    setText("daq-crc", fmtInt(daq.crc_failures));
    setText("daq-gaps", fmtInt(daq.sequence_gaps));
    $("daq-crc").dataset.level = daq.crc_failures ? "warn" : "";
    $("daq-gaps").dataset.level = daq.sequence_gaps ? "warn" : "";
    setFlag("bench-connected", s.connected, true);
    setFlag("bench-busy", s.busy, false, "busy", "idle");
    $("bench-busy").dataset.level = s.busy ? "warn" : "ok";
    setText("bench-updated", s.updated_at ? "updated " + shortTime(s.updated_at) : "");
    const err = $("bench-error");
    if (s.error) {
      err.textContent = "bench error: " + detailText(s.error);
      err.hidden = false;
    } else {
      err.hidden = true;
    }
  }

  function setLive(mode, text) {
    const el = $("live-mode");
    el.dataset.mode = mode;
    el.textContent = text;
  }

  async function pollStatus() {
    try {
      renderStatus(await apiGet("/bench/status"));
      if (Date.now() - lastBenchAt > SSE_STALE_MS) setLive("poll", "polling every 2 s");
    } catch (e) {
      setLive("down", "service unreachable");
    }
  }

  // ---------------------------------------------------------------- SSE
  let es = null;
  let sseWasDown = false;

  function startEvents() {
    if (!window.EventSource) return;
    es = new EventSource(API + "/events");
    es.addEventListener("open", () => {
      if (sseWasDown) {
        // we may have missed sweep progress while the stream was down
        sseWasDown = false;
        loadSweeps();
        loadMaps(false);
      }
    });
    es.addEventListener("error", () => {
      sseWasDown = true;
      if (es.readyState === EventSource.CLOSED) {
        // the browser gave up (e.g. HTTP error); retry ourselves later, poll meanwhile
        es = null;
        setTimeout(startEvents, 10000);
      }
    });
    es.addEventListener("bench.status", (ev) => {
      const s = parse(ev);
      if (!s) return;
      lastBenchAt = Date.now();
      setLive("live", "live");
      renderStatus(s);
    });
    es.addEventListener("sweep.progress", (ev) => {
      const p = parse(ev);
      if (p) onSweepProgress(p);
    });
    es.addEventListener("sweep.point", (ev) => {
      const p = parse(ev);
      if (p) onSweepPoint(p);
    });
    es.addEventListener("job.state", (ev) => {
      const p = parse(ev);
      if (!p) return;
      if (p.kind === "sweep") scheduleSweepReload();
      else onJobState(p);
    });
  }

  function parse(ev) {
    try {
      return JSON.parse(ev.data);
    } catch (_) {
      return null;
    }
  }

  // Fallback: whenever no bench.status has arrived over SSE recently, poll.
  setInterval(() => {
    if (Date.now() - lastBenchAt > SSE_STALE_MS) pollStatus();
  }, POLL_MS);
  setInterval(() => {
    if (Date.now() - lastBenchAt > SSE_STALE_MS) loadSweeps();
  }, SWEEP_POLL_MS);

  // ---------------------------------------------------------------- (2) sweeps
  const sweeps = new Map();     // id -> sweep object
  const lastPoint = new Map();  // sweep id -> text of its last finished point
  let sweepReloadTimer = null;

  function scheduleSweepReload() {
    if (sweepReloadTimer) return;
    sweepReloadTimer = setTimeout(() => {
      sweepReloadTimer = null;
      loadSweeps();
    }, 300);
  }

  async function loadSweeps() {
    try {
      const list = await apiGet("/sweeps");
      sweeps.clear();
      for (const s of list) sweeps.set(s.id, s);
      renderSweeps();
    } catch (e) {
      /* shown by the live indicator; keep the last list */
    }
  }

  function gridSummary(g) {
    if (!g) return "—";
    const part = (arr, unit, sym) => {
      if (!Array.isArray(arr)) return null;
      const vals = arr.length > 4 ? `${arr.length} values ${arr[0]}…${arr[arr.length - 1]}` : arr.join(", ");
      return `${sym} ${vals} ${unit}`;
    };
    return [part(g.torque_nm, "N·m", "T"), part(g.speed_rpm, "rpm", "n"), part(g.udc_v, "V", "U")]
      .filter(Boolean).join(" · ");
  }

  function gridFull(g) {
    if (!g) return "";
    return `torque ${JSON.stringify(g.torque_nm)} N·m\nspeed ${JSON.stringify(g.speed_rpm)} rpm\n` +
      `U_dc ${JSON.stringify(g.udc_v)} V`;
  }

  function el(tag, attrs, text) {
    const e = document.createElement(tag);
    if (attrs) for (const [k, v] of Object.entries(attrs)) {
      if (k === "dataset") Object.assign(e.dataset, v);
      else e.setAttribute(k, v);
    }
    if (text !== undefined) e.textContent = text;
    return e;
  }

  function renderSweeps() {
    const body = $("sweep-rows");
    const rows = [...sweeps.values()].sort((a, b) => b.id - a.id);
    $("sweep-empty").hidden = rows.length > 0;
    body.replaceChildren(...rows.map(sweepRow));
  }

  function sweepRow(s) {
    const tr = el("tr", { "data-testid": "sweep-row", "data-sweep-id": String(s.id), "data-state": s.state });
    tr.appendChild(el("td", { class: "num" }, String(s.id)));
    tr.appendChild(el("td", null)).appendChild(el("span", { class: "badge", "data-level": sweepLevel(s.state),
      "data-testid": "sweep-state" }, s.state));
    tr.appendChild(el("td", null, s.method || "—"));
    tr.appendChild(el("td", { class: "grid-cell", title: gridFull(s.grid) }, gridSummary(s.grid)));

    const td = el("td", { class: "wide" });
    const prog = s.progress || {};
    const done = Number(prog.done) || 0;
    const total = Number(prog.total) || 0;
    const bar = el("div", { class: "bar", "data-testid": "sweep-progress", "data-level": sweepLevel(s.state) });
    const fill = el("div", { class: "fill" });
    fill.style.width = total ? `${Math.min(100, (100 * done) / total).toFixed(1)}%` : "0%";
    bar.appendChild(fill);
    bar.appendChild(el("span", { class: "bar-text" }, `${done} / ${total}`));
    td.appendChild(bar);
    // outcomes apart: only ok cells go into a LUT
    const outcome = ["ok", "below_target", "no_authority", "failed"]
      .filter((k) => Number(prog[k]) > 0).map((k) => `${prog[k]} ${k.replace("_", " ")}`);
    if (outcome.length) td.appendChild(el("div", { class: "row-note", "data-testid": "sweep-outcome" }, outcome.join(" · ")));
    if (s.error) td.appendChild(el("div", { class: "row-error", "data-testid": "sweep-row-error" }, detailText(s.error)));
    else if (lastPoint.has(s.id) && (s.state === "running" || s.state === "paused")) {
      td.appendChild(el("div", { class: "row-note" }, lastPoint.get(s.id)));
    }
    tr.appendChild(td);

    const mapTd = el("td", { class: "map-cell" });
    if (s.map_id !== null && s.map_id !== undefined) {
      const a = el("a", { href: "#map" }, `map ${s.map_id}`);
      a.addEventListener("click", (ev) => {
        ev.preventDefault();
        selectMap(s.map_id);
      });
      mapTd.appendChild(a);
    } else mapTd.textContent = "—";
    tr.appendChild(mapTd);
    tr.appendChild(el("td", { class: "time" }, shortTime(s.created_at)));

    const act = el("td", { class: "actions" });
    const button = (label, action) => {
      const b = el("button", { type: "button", class: "small", "data-action": action }, label);
      b.addEventListener("click", () => sweepAction(s.id, action));
      act.appendChild(b);
    };
    if (s.state === "running" || s.state === "queued") button("pause", "pause");
    if (s.state === "paused") button("resume", "resume");
    if (s.state === "running" || s.state === "queued" || s.state === "paused") button("cancel", "cancel");
    tr.appendChild(act);
    return tr;
  }

  function sweepLevel(state) {
    switch (state) {
      case "done": return "ok";
      case "running": return "run";
      case "failed": return "bad";
      case "cancelled": case "paused": return "warn";
      default: return "idle";
    }
  }

  async function sweepAction(id, action) {
    showMsg("sweep-error", null);
    try {
      const s = await apiPost(`/sweeps/${id}/${action}`);
      if (s && s.id !== undefined) sweeps.set(s.id, s);
      renderSweeps();
      scheduleSweepReload();
    } catch (e) {
      showMsg("sweep-error", e.lines || [String(e.message || e)], `${action} sweep ${id} failed (HTTP ${e.status || "?"})`);
    }
  }

  function onSweepProgress(p) {
    const s = sweeps.get(p.sweep_id);
    if (!s) {
      scheduleSweepReload();
    } else {
      s.state = p.state || s.state;
      s.progress = { done: p.done, total: p.total };
      if (p.map_id !== undefined && p.map_id !== null) s.map_id = p.map_id;
      renderSweeps();
      if (["done", "failed", "cancelled"].includes(p.state)) scheduleSweepReload();
    }
    if (p.state === "done" && p.map_id !== null && p.map_id !== undefined) {
      loadMaps(false).then(() => {
        selectMap(p.map_id);
        showMsg("map-note", [`Sweep ${p.sweep_id} finished — showing its map ${p.map_id}.`]);
      });
    }
  }

  function onSweepPoint(p) {
    const op = p.operating_point || {};
    const r = p.result || {};
    let text = `last: T ${fmt(op.torque_nm)} N·m, n ${fmt(op.speed_rpm)} rpm, U ${fmt(op.udc_v)} V — ${p.state}`;
    if (p.result) {
      text += `, γ ${fmt(r.gamma_deg, 2)}°, δ ${fmt(r.delta_deg, 1)}°`;
      if (r.suppression_db !== undefined && r.suppression_db !== null) text += `, ${fmt(r.suppression_db, 1)} dB`;
    }
    lastPoint.set(p.sweep_id, text);
    if (sweeps.has(p.sweep_id)) renderSweeps();
  }

  function parseList(str, name) {
    const parts = str.split(/[,;\s]+/).map((x) => x.trim()).filter((x) => x !== "");
    if (parts.length === 0) return { error: `${name}: enter at least one number` };
    const vals = [];
    for (const p of parts) {
      const v = Number(p);
      if (!Number.isFinite(v)) return { error: `${name}: "${p}" is not a number` };
      vals.push(v);
    }
    return { vals };
  }

  async function submitSweep(ev) {
    ev.preventDefault();
    showMsg("sweep-error", null);
    showMsg("sweep-ok", null);
    const f = ev.target;
    const fields = [["torque_nm", "torque"], ["speed_rpm", "speed"], ["udc_v", "DC link voltage"]];
    const grid = {};
    const errs = [];
    for (const [key, label] of fields) {
      const r = parseList(f.elements[key].value, label);
      if (r.error) errs.push(r.error);
      else grid[key] = r.vals;
    }
    if (errs.length) {
      showMsg("sweep-error", errs, "Check the grid:");
      return;
    }
    const btn = $("sweep-submit");
    btn.disabled = true;
    try {
      const s = await apiPost("/sweeps", { grid, method: f.elements.method.value });
      if (s && s.id !== undefined) {
        sweeps.set(s.id, s);
        renderSweeps();
        const n = s.progress && s.progress.total;
        showMsg("sweep-ok", [`Sweep ${s.id} accepted (${s.state}${n ? `, ${n} operating points` : ""}).`]);
      }
      scheduleSweepReload();
    } catch (e) {
      showMsg("sweep-error", e.lines || [String(e.message || e)],
        e.status ? `Sweep rejected (HTTP ${e.status}):` : "Sweep request failed:");
    } finally {
      btn.disabled = false;
    }
  }

  // ---------------------------------------------------------------- (3) maps
  let currentMap = null;      // full map object
  let mapsList = [];

  async function loadMaps(selectNewest) {
    try {
      mapsList = await apiGet("/maps");
    } catch (e) {
      return;
    }
    const sel = $("map-select");
    const prev = sel.value;
    sel.replaceChildren(...mapsList.slice().sort((a, b) => b.id - a.id).map((m) =>
      el("option", { value: String(m.id) },
        `map ${m.id} · sweep ${m.sweep_id} · h=${m.harmonic_order} · ${shortTime(m.created_at)}`)));
    $("map-empty").hidden = mapsList.length > 0;
    $("map").dataset.empty = mapsList.length === 0 ? "1" : "";
    if (mapsList.length === 0) return;
    if (!selectNewest && prev && mapsList.some((m) => String(m.id) === prev)) {
      sel.value = prev;
    } else {
      sel.value = sel.options[0].value;
      await showMap(Number(sel.value));
    }
  }

  async function selectMap(id) {
    const sel = $("map-select");
    if (![...sel.options].some((o) => o.value === String(id))) await loadMaps(false);
    sel.value = String(id);
    await showMap(id);
  }

  async function showMap(id) {
    showMsg("map-note", null);
    for (const a of document.querySelectorAll("#map-exports a")) {
      a.href = `${API}/maps/${id}/export?format=${a.dataset.format}`;
      a.setAttribute("download", "");
    }
    let m;
    try {
      m = await apiGet(`/maps/${id}`);
    } catch (e) {
      showMsg("map-note", [`map ${id}: ${e.message}`]);
      return;
    }
    currentMap = m;
    const udcs = (m.axes && m.axes.udc_v) || [...new Set(m.cells.map((c) => c.udc_v))].sort((a, b) => a - b);
    const usel = $("udc-select");
    const prev = usel.value;
    usel.replaceChildren(...udcs.map((u) => el("option", { value: String(u) }, `${u} V`)));
    if (udcs.some((u) => String(u) === prev)) usel.value = prev;
    const counts = {};
    for (const c of m.cells) counts[c.status] = (counts[c.status] || 0) + 1;
    const countText = Object.entries(counts).map(([k, v]) => `${v} ${k}`).join(", ");
    setText("map-meta", `h = ${m.harmonic_order} · method ${m.method || "—"} · sweep ${m.sweep_id} · ` +
      `sw ${m.software_version || "—"} · ${m.cells.length} cells (${countText})`);
    drawMap();
  }

  // gamma = |theta| (>= 0, clamped to gamma_max); delta = -atan2(theta_sin, theta_cos) is a phase,
  // so it gets a cyclic colour scale over a full turn.
  const CYCLIC = [[0, "#3b6fb6"], [0.25, "#3aa57a"], [0.5, "#e8c547"], [0.75, "#d1495b"], [1, "#3b6fb6"]];
  const PLOTS = [
    { div: "plot-gamma", key: "gamma_deg", title: "γ — injection amplitude", unit: "deg", cbar: "γ (°)", sym: "γ",
      scale: "Viridis", range: "zero", digits: 2 },
    { div: "plot-delta", key: "delta_deg", title: "δ — injection phase", unit: "deg", cbar: "δ (°)", sym: "δ",
      scale: CYCLIC, range: "phase", digits: 1 },
    { div: "plot-supp", key: "suppression_db", title: "suppression of the h-th harmonic", unit: "dB", cbar: "dB",
      sym: "suppression", scale: "Cividis", range: "auto", digits: 1 },
  ];

  function drawMap() {
    if (!window.Plotly || !currentMap) return;
    const m = currentMap;
    const udc = Number($("udc-select").value);
    const cells = m.cells.filter((c) => Number(c.udc_v) === udc);
    const xs = ((m.axes && m.axes.torque_nm) || [...new Set(cells.map((c) => c.torque_nm))]).slice().sort((a, b) => a - b);
    const ys = ((m.axes && m.axes.speed_rpm) || [...new Set(cells.map((c) => c.speed_rpm))]).slice().sort((a, b) => a - b);
    const xi = new Map(xs.map((v, i) => [Number(v), i]));
    const yi = new Map(ys.map((v, i) => [Number(v), i]));

    for (const p of PLOTS) {
      const z = ys.map(() => xs.map(() => null));
      const text = ys.map((n) => xs.map((t) =>
        `T* ${t} N·m<br>n ${n} rpm<br>U<sub>dc</sub> ${udc} V<br><i>no cell</i>`));
      for (const c of cells) {
        const i = yi.get(Number(c.speed_rpm));
        const j = xi.get(Number(c.torque_nm));
        if (i === undefined || j === undefined) continue;
        const head = `T* ${fmt(c.torque_nm)} N·m<br>n ${fmt(c.speed_rpm)} rpm<br>U<sub>dc</sub> ${fmt(c.udc_v)} V<br>`;
        const v = c[p.key];
        if (c.status === "ok" && v !== null && v !== undefined) {
          z[i][j] = v;
          text[i][j] = head + `<b>${p.sym} = ${Number(v).toFixed(p.digits)} ${p.unit === "deg" ? "°" : p.unit}</b>` +
            (c.result_id ? "<br><i>click: result details</i>" : "");
        } else {
          text[i][j] = head + `<b>status: ${escapeHtml(String(c.status))}</b> (no value)` +
            (c.result_id ? "<br><i>click: result details</i>" : "");
        }
      }
      const trace = {
        type: "heatmap", x: xs, y: ys, z, text, hovertemplate: "%{text}<extra></extra>",
        hoverongaps: true, colorscale: p.scale,
        xgap: 1, ygap: 1,
        colorbar: { title: { text: p.cbar, side: "right" }, thickness: 12, len: 0.9 },
      };
      const finite = z.flat().filter((v) => v !== null);
      if (p.range === "zero" && finite.length) {
        trace.zmin = 0;
        trace.zmax = Math.max(...finite, 1e-6);
      } else if (p.range === "phase") {
        const lo = finite.length ? Math.min(...finite) : 0;
        const hi = finite.length ? Math.max(...finite) : 0;
        [trace.zmin, trace.zmax] = (lo >= 0 && hi > 180) ? [0, 360] : [-180, 180];
        trace.colorbar.tickvals = trace.zmin === 0 ? [0, 90, 180, 270, 360] : [-180, -90, 0, 90, 180];
      }
      const layout = {
        title: { text: `${p.title} (${p.unit}) @ U<sub>dc</sub> = ${udc} V`, font: { size: 13 }, x: 0.02, xanchor: "left" },
        margin: { l: 58, r: 10, t: 36, b: 44 },
        xaxis: { title: { text: "torque T* (N·m)" }, tickvals: xs.length <= 12 ? xs : undefined, zeroline: false },
        yaxis: { title: { text: "speed n (rpm)" }, tickvals: ys.length <= 12 ? ys : undefined, zeroline: false },
        font: { family: "system-ui, -apple-system, Segoe UI, Roboto, sans-serif", size: 11 },
        paper_bgcolor: "rgba(0,0,0,0)", plot_bgcolor: "#eceff3",
      };
      window.Plotly.react(p.div, [trace], layout, { displaylogo: false, responsive: true });
      bindMapClick(p.div);
    }
  }

  // A click on a map cell opens the stored result of that cell in the result view.
  function bindMapClick(divId) {
    const div = $(divId);
    if (div.dataset.clickBound || typeof div.on !== "function") return;
    div.dataset.clickBound = "1";
    div.on("plotly_click", (ev) => {
      const pt = ev && ev.points && ev.points[0];
      if (!pt || !currentMap) return;
      const udc = Number($("udc-select").value);
      const cell = currentMap.cells.find((c) => Number(c.torque_nm) === Number(pt.x) &&
        Number(c.speed_rpm) === Number(pt.y) && Number(c.udc_v) === udc);
      if (!cell) return;
      if (cell.result_id === null || cell.result_id === undefined) {
        showMsg("map-note", [`No stored result for T* ${fmt(cell.torque_nm)} N·m, n ${fmt(cell.speed_rpm)} rpm, ` +
          `U_dc ${fmt(cell.udc_v)} V (status ${cell.status}).`]);
        return;
      }
      openResult(cell.result_id, `map ${currentMap.id}`);
    });
  }

  function escapeHtml(s) {
    return s.replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" }[c]));
  }

  // ---------------------------------------------------------------- (4) identify one operating point
  const JOB_ACTIVE = new Set(["queued", "running"]);
  const JOB_POLL_MS = 1000;        // job poll period while SSE is down
  const JOB_POLL_LIVE_MS = 2500;   // safety-net poll while SSE is live (job.state triggers a fetch)
  const OPTION_EXAMPLES = {
    adaptive: '{"mu_per_s": 25, "max_blocks": 40}',
    probe: '{"probe_max_deg": 4.0, "max_newton_steps": 4}',
    grid: '{"gamma_step_deg": 0.5, "delta_step_deg": 20}',
  };
  const OP_FIELDS = [["torque_nm", "torque T*", "identify-torque"], ["speed_rpm", "speed n", "identify-speed"],
    ["udc_v", "DC link voltage", "identify-udc"]];
  let job = null;                  // the identification job the panel follows
  let jobTimer = null;
  let jobFetching = false;
  const seenJobStates = new Map(); // job id -> last state seen over SSE (may arrive before the POST answers)

  function jobLevel(state) {
    return sweepLevel(state);
  }

  function markInvalid(names) {
    const ids = { torque_nm: "identify-torque", speed_rpm: "identify-speed", udc_v: "identify-udc",
      method: "identify-method", options: "identify-options" };
    for (const [name, id] of Object.entries(ids)) {
      if (names.has(name)) $(id).setAttribute("aria-invalid", "true");
      else $(id).removeAttribute("aria-invalid");
    }
  }

  async function submitIdentify(ev) {
    ev.preventDefault();
    showMsg("identify-error", null);
    const f = ev.target;
    const errs = [];
    const bad = new Set();
    const op = {};
    for (const [key, label] of OP_FIELDS) {
      const raw = f.elements[key].value.trim();
      const v = Number(raw);
      if (raw === "") {
        errs.push(`${label}: enter a number`);
        bad.add(key);
      } else if (!Number.isFinite(v)) {
        errs.push(`${label}: "${raw}" is not a number`);
        bad.add(key);
      } else op[key] = v;
    }
    let options = {};
    const rawOpts = f.elements.options.value.trim();
    if (rawOpts) {
      try {
        options = JSON.parse(rawOpts);
        if (options === null || typeof options !== "object" || Array.isArray(options)) {
          errs.push('options: must be a JSON object, e.g. {"name": value}');
          bad.add("options");
        }
      } catch (e) {
        errs.push(`options: not valid JSON (${e.message})`);
        bad.add("options");
      }
    }
    markInvalid(bad);
    if (errs.length) {
      showMsg("identify-error", errs, "Check the inputs:");
      return;
    }
    const btn = $("identify-submit");
    btn.disabled = true;
    try {
      const j = await apiPost("/identifications", { operating_point: op, method: f.elements.method.value, options });
      followJob(j);
    } catch (e) {
      if (e.status === 422 && Array.isArray(e.detail)) {
        const names = new Set();
        for (const d of e.detail) for (const p of (Array.isArray(d.loc) ? d.loc : [])) names.add(String(p));
        markInvalid(names);
      }
      showMsg("identify-error", e.lines || [String(e.message || e)],
        e.status ? `Identification rejected (HTTP ${e.status}):` : "Identification request failed:");
    } finally {
      btn.disabled = false;
    }
  }

  function followJob(j) {
    const same = job && job.id === j.id;
    const handled = same && job.handled;
    job = Object.assign({}, j, { handled });
    renderJob();
    if (JOB_ACTIVE.has(job.state)) {
      const seen = seenJobStates.get(job.id);
      scheduleJobPoll(seen && seen !== job.state ? 0 : undefined);
    } else onJobFinished();
  }

  function scheduleJobPoll(delay) {
    clearTimeout(jobTimer);
    const live = Date.now() - lastBenchAt <= SSE_STALE_MS;
    jobTimer = setTimeout(refreshJob, delay !== undefined ? delay : (live ? JOB_POLL_LIVE_MS : JOB_POLL_MS));
  }

  async function refreshJob() {
    if (!job || jobFetching) return;
    jobFetching = true;
    const id = job.id;
    try {
      const j = await apiGet(`/jobs/${id}`);
      if (job && job.id === id) followJob(j);
    } catch (e) {
      if (job && job.id === id) {
        setText("identify-note", `cannot read job ${id}: ${e.message} — retrying`);
        scheduleJobPoll(JOB_POLL_MS * 2);
      }
    } finally {
      jobFetching = false;
    }
  }

  function onJobState(p) {
    seenJobStates.set(p.job_id, p.state);
    if (seenJobStates.size > 200) seenJobStates.delete(seenJobStates.keys().next().value);
    if (job && p.job_id === job.id && p.state !== job.state) {
      job.state = p.state;      // show the new state at once; the fetch brings the rest
      renderJob();
      scheduleJobPoll(0);
    }
  }

  function renderJob() {
    $("identify-job").hidden = !job;
    if (!job) return;
    setText("identify-job-id", String(job.id));
    const st = $("identify-state");
    st.textContent = job.state;
    st.dataset.state = job.state;
    st.dataset.level = jobLevel(job.state);
    $("identify-cancel").hidden = !JOB_ACTIVE.has(job.state);
    const req = job.request || {};
    const op = req.operating_point || {};
    const what = `${req.method || "?"} at T* ${fmt(op.torque_nm)} N·m, n ${fmt(op.speed_rpm)} rpm, U ${fmt(op.udc_v)} V`;
    let note = what;
    if (job.state === "queued") note += " — waiting for the bench";
    else if (job.state === "running") note += job.started_at ? ` — running since ${shortTime(job.started_at)}` : " — running";
    else if (job.state === "done" && job.result) {
      const r = job.result;
      note += r.status === "ok"
        ? ` — γ ${fmt(r.gamma_deg, 2)}°, δ ${fmt(r.delta_deg, 1)}°, ${fmt(r.suppression_db, 1)} dB (result below)`
        : ` — result status ${r.status}`;
    } else if (job.state === "failed") note += " — failed";
    else if (job.state === "cancelled") note += " — cancelled";
    setText("identify-note", note, job.error ? String(job.error) : "");
  }

  function onJobFinished() {
    clearTimeout(jobTimer);
    if (!job || job.handled) return;
    job.handled = true;
    if (job.state === "failed") {
      showMsg("identify-error", [job.error ? detailText(job.error) : "no reason given"], `Job ${job.id} failed:`);
    }
    if (job.result) showResult(job.result, `identification job ${job.id}`);
    else if (job.state === "done") setText("identify-note", `job ${job.id} finished without a stored result`);
  }

  async function cancelJob() {
    if (!job) return;
    showMsg("identify-error", null);
    const id = job.id;
    try {
      followJob(await apiPost(`/jobs/${id}/cancel`));
    } catch (e) {
      showMsg("identify-error", e.lines || [String(e.message || e)], `cancel job ${id} failed (HTTP ${e.status || "?"})`);
      scheduleJobPoll(0);
    }
  }

  // After a reload: keep following an identification that is still queued or running.
  async function resumeJob() {
    try {
      const list = await apiGet("/jobs?limit=10");
      const j = list.find((x) => x.kind === "identification" && JOB_ACTIVE.has(x.state));
      if (j && !job) followJob(j);
    } catch (_) { /* nothing to resume */ }
  }

  // ---------------------------------------------------------------- (5) result view (Fig. 8, 9, 10)
  const FONT = { family: "system-ui, -apple-system, Segoe UI, Roboto, sans-serif", size: 11 };
  const C_BEFORE = "#9aa4b2";
  const C_AFTER = "#1b5fae";
  const C_COS = "#1b5fae";
  const C_SIN = "#d1495b";
  let resultSeq = 0;                // guards against a slow fetch overwriting a newer result

  function sig(v, n) {
    if (v === null || v === undefined) return "—";
    const x = Number(v);
    if (!Number.isFinite(x)) return String(v);
    if (x === 0) return "0";
    const a = Math.abs(x);
    if (a >= 1e5 || a < 1e-3) return x.toExponential((n || 4) - 1);
    return String(Number(x.toPrecision(n || 4)));
  }

  function unitOf(key) {
    const k = String(key);
    if (/_deg$/.test(k)) return "°";
    if (/_db$/.test(k)) return "dB";
    if (/_per_s$/.test(k)) return "1/s";
    if (/_s$/.test(k)) return "s";
    if (/_fs$/.test(k)) return "FS";
    if (/_rpm$/.test(k)) return "rpm";
    if (/_rad$/.test(k)) return "rad";
    if (/_samples$|^stale_samples$/.test(k)) return "samples";
    return "";
  }

  function valueText(v) {
    if (v === null || v === undefined) return "—";
    if (typeof v === "boolean") return v ? "yes" : "no";
    if (typeof v === "number") return sig(v, 5);
    if (Array.isArray(v)) return JSON.stringify(v, (_, x) => (typeof x === "number" ? Number(sig(x, 4)) : x));
    return String(v);
  }

  // details {a: 1, fit: {gamma_deg: 3}} -> [["a", 1], ["fit.gamma_deg", 3]]
  function flatten(obj, prefix, out) {
    for (const [k, v] of Object.entries(obj || {})) {
      const key = prefix ? `${prefix}.${k}` : k;
      if (v && typeof v === "object" && !Array.isArray(v)) flatten(v, key, out);
      else out.push([key, v]);
    }
    return out;
  }

  function resultLevel(status) {
    if (status === "ok") return "ok";
    if (status === "no_authority" || status === "below_target") return "warn";
    return "bad";
  }

  async function openResult(id, source) {
    const seq = ++resultSeq;
    showMsg("result-message", null);
    try {
      const r = await apiGet(`/results/${id}`);
      if (seq !== resultSeq) return;
      showResult(r, source, seq);
      $("result").scrollIntoView({ behavior: "smooth", block: "start" });
    } catch (e) {
      if (seq !== resultSeq) return;
      showMsg("result-message", [`result ${id}: ${e.message}`]);
    }
  }

  function showResult(r, source, seq) {
    if (seq === undefined) resultSeq++;
    const d = r.details || {};
    const op = r.operating_point || {};
    $("result").dataset.empty = "";
    $("result").dataset.resultId = String(r.id);
    $("result-empty").hidden = true;
    setText("result-title", `#${r.id} · ${r.method} · T* ${fmt(op.torque_nm)} N·m · n ${fmt(op.speed_rpm)} rpm · ` +
      `U_dc ${fmt(op.udc_v)} V · h = ${fmt(r.harmonic_order)}` + (source ? ` · from ${source}` : ""));
    const st = $("result-status");
    st.hidden = false;
    st.textContent = r.status || "—";
    st.dataset.level = resultLevel(r.status);
    const message = r.message || r.error;
    if (r.status !== "ok") {
      showMsg("result-message", [message ? String(message) : "no message"], `status ${r.status}:`);
    } else {
      showMsg("result-message", null);
    }

    setText("result-gamma", fmt(r.gamma_deg, 2));
    setText("result-delta", fmt(r.delta_deg, 1));
    setText("result-suppression", fmt(r.suppression_db, 1));
    setText("result-plant-time", fmt(r.plant_time_s, 3));

    const facts = [];
    const fact = (label, value, unit, title) => {
      if (value === null || value === undefined || value === "") return;
      facts.push([label, value, unit || "", title]);
    };
    fact("θ_cos", sig(r.theta_cos, 5), "rad");
    fact("θ_sin", sig(r.theta_sin, 5), "rad");
    if (r.uncompensated) fact("|a| before", sig(r.uncompensated.amplitude), "FS", "h-th harmonic amplitude, no injection");
    if (r.residual) fact("|a| after", sig(r.residual.amplitude), "FS", "h-th harmonic amplitude with the identified θ");
    if (d.time_to_40db_s !== undefined) fact("time to −40 dB", sig(d.time_to_40db_s), "s", "plant time until the h-th amplitude fell 40 dB");
    if (d.model_phase_error_deg !== undefined) fact("model phase error", sig(d.model_phase_error_deg), "°", "phase of Ŝ (model) against the measured S");
    if (d.model_gain_error_db !== undefined) fact("model gain error", sig(d.model_gain_error_db), "dB", "gain of Ŝ (model) against the measured S");
    if (r.s_model) fact("Ŝ model", `${sig(r.s_model.gain)} ∠ ${sig(r.s_model.phase_deg)}°`, "", "secondary path model (eq. 14-20): gain ∠ phase");
    if (r.s_measured) fact("S measured", `${sig(r.s_measured.gain)} ∠ ${sig(r.s_measured.phase_deg)}°`, "", "secondary path measured online: gain ∠ phase");
    if (d.minimum) fact("grid minimum", `γ ${sig(d.minimum.gamma_deg)}°, δ ${sig(d.minimum.delta_deg)}°, |a| ${sig(d.minimum.amplitude_fs)} FS`, "");
    if (d.fit) fact("affine fit", `γ ${sig(d.fit.gamma_deg)}°, δ ${sig(d.fit.delta_deg)}°, rms ${sig(d.fit.rms_fs)} FS`, "");
    if (d.reported) fact("reported", String(d.reported), "", "which grid theta the result reports and verifies");
    if (d.converged !== undefined) fact("converged", d.converged ? "yes" : "no", d.diverged ? "(diverged)" : "");
    fact("windows used", r.windows_used !== undefined && r.windows_used !== null
      ? `${r.windows_used}${r.windows_discarded ? ` (+${r.windows_discarded} discarded)` : ""}` : null, "");
    if (message && r.status === "ok") fact("message", String(message), "");
    fact("bench", r.bench_identity, "");
    fact("software", r.software_version, "");
    fact("finished", r.finished_at ? shortTime(r.finished_at) : null, "");
    const dl = $("result-facts");
    dl.replaceChildren();
    for (const [label, value, unit, title] of facts) {
      const dt = el("dt", title ? { title } : null, label);
      const dd = el("dd", null);
      dd.appendChild(el("span", { class: "num" }, String(value)));
      if (unit) dd.appendChild(el("span", { class: "unit" }, unit));
      dl.append(dt, dd);
    }

    const tbody = $("result-details").tBodies[0];
    tbody.replaceChildren(...flatten(d, "", []).map(([k, v]) => {
      const tr = el("tr", null);
      tr.append(el("th", null, k), el("td", { class: "num" }, valueText(v)), el("td", { class: "unit" }, unitOf(k.split(".").pop())));
      return tr;
    }));
    setText("result-options", r.options ? "options: " + JSON.stringify(r.options) : "");

    drawResult(r);
  }

  function baseLayout(title, xTitle, yTitle, extra) {
    return Object.assign({
      title: { text: title, font: { size: 13 }, x: 0.02, xanchor: "left" },
      margin: { l: 64, r: 12, t: 36, b: 44 },
      xaxis: { title: { text: xTitle }, zeroline: false },
      yaxis: { title: { text: yTitle }, zeroline: false },
      legend: { orientation: "h", x: 1, xanchor: "right", y: 1.02, yanchor: "bottom", font: { size: 10 } },
      font: FONT, paper_bgcolor: "rgba(0,0,0,0)", plot_bgcolor: "#f7f8fa",
    }, extra || {});
  }

  const PLOT_CONFIG = { displaylogo: false, responsive: true };

  function showFigure(divId, on) {
    const fig = $(divId).closest("figure");
    fig.hidden = !on;
    if (!on && window.Plotly) window.Plotly.purge(divId);
  }

  function column(rows, names, name, fallback) {
    const i = Array.isArray(names) ? names.indexOf(name) : -1;
    const k = i >= 0 ? i : fallback;
    return rows.map((row) => (Array.isArray(row) ? row[k] : null));
  }

  function drawResult(r) {
    if (!window.Plotly) {
      setText("result-note", "Plotly.js did not load — plots cannot be drawn.");
      return;
    }
    const tr = r.traces || {};
    const d = r.details || {};
    const notes = [];

    // Fig. 9: theta and the h-th amplitude over plant time
    const hist = Array.isArray(tr.theta_history) ? tr.theta_history : [];
    const hasHist = hist.length > 0;
    showFigure("plot-theta", hasHist);
    showFigure("plot-amplitude", hasHist);
    if (hasHist) {
      const cols = tr.theta_history_columns;
      const t = column(hist, cols, "plant_time_s", 0);
      const tc = column(hist, cols, "theta_cos", 1);
      const ts = column(hist, cols, "theta_sin", 2);
      const amp = column(hist, cols, "amplitude_fs", 3);
      window.Plotly.react("plot-theta", [
        { x: t, y: tc, name: "θ_cos", mode: "lines+markers", line: { color: C_COS, width: 2 }, marker: { size: 5 },
          hovertemplate: "t %{x:.4f} s<br>θ_cos %{y:.5f} rad<extra></extra>" },
        { x: t, y: ts, name: "θ_sin", mode: "lines+markers", line: { color: C_SIN, width: 2 }, marker: { size: 5 },
          hovertemplate: "t %{x:.4f} s<br>θ_sin %{y:.5f} rad<extra></extra>" },
      ], baseLayout(`Fig. 9 — θ transient (${escapeHtml(String(r.method))})`, "plant time t (s)", "θ (rad)"), PLOT_CONFIG);

      const shapes = [];
      const annotations = [];
      const u0 = r.uncompensated && Number(r.uncompensated.amplitude);
      if (u0 > 0) {
        shapes.push({ type: "line", xref: "paper", x0: 0, x1: 1, y0: u0 / 100, y1: u0 / 100,
          line: { color: "#667085", width: 1, dash: "dot" } });
        annotations.push({ xref: "paper", x: 1, y: Math.log10(u0 / 100), text: "−40 dB", showarrow: false,
          xanchor: "right", yanchor: "bottom", font: { size: 10, color: "#667085" } });
      }
      if (Number.isFinite(Number(d.time_to_40db_s))) {
        shapes.push({ type: "line", yref: "paper", y0: 0, y1: 1, x0: d.time_to_40db_s, x1: d.time_to_40db_s,
          line: { color: "#3a9d63", width: 1, dash: "dash" } });
      }
      const ampTraces = [{ x: t, y: amp, name: "|a_h| per window", mode: "lines+markers",
        line: { color: C_AFTER, width: 2 }, marker: { size: 5 },
        hovertemplate: "t %{x:.4f} s<br>|a| %{y:.3e} FS<extra></extra>" }];
      if (r.residual && Number(r.residual.amplitude) > 0 && Number.isFinite(Number(r.plant_time_s))) {
        ampTraces.push({ x: [r.plant_time_s], y: [r.residual.amplitude], name: "verified residual", mode: "markers",
          marker: { symbol: "star", size: 11, color: "#3a9d63" },
          hovertemplate: "t %{x:.4f} s<br>residual |a| %{y:.3e} FS<extra></extra>" });
      }
      window.Plotly.react("plot-amplitude", ampTraces,
        baseLayout(`Fig. 9 — h-th harmonic amplitude (h = ${escapeHtml(fmt(r.harmonic_order))})`, "plant time t (s)",
          "|a_h| (FS, log)", { shapes, annotations,
            yaxis: { title: { text: "|a_h| (FS, log)" }, type: "log", exponentformat: "power" } }), PLOT_CONFIG);
    } else {
      notes.push(`no θ transient for method ${r.method}`);
    }

    // Fig. 10: spectrum before / after and the alpha snippets
    const sb = Array.isArray(tr.spectrum_before) ? tr.spectrum_before : [];
    const sa = Array.isArray(tr.spectrum_after) ? tr.spectrum_after : [];
    const hasSpec = sb.length > 0 || sa.length > 0;
    showFigure("plot-spectrum", hasSpec);
    if (hasSpec) {
      const orders = (arr) => arr.map((_, i) => i + 1);
      const h = Number(r.harmonic_order);
      const hb = sb[h - 1];
      const ha = sa[h - 1];
      const annotations = [];
      if (Number.isFinite(h) && (hb > 0 || ha > 0)) {
        annotations.push({ x: h, y: Math.log10(Math.max(hb || 0, ha || 0)), text: `h = ${h}`, showarrow: true,
          arrowhead: 0, ax: 24, ay: -18, font: { size: 10 } });
      }
      const n = Math.max(sb.length, sa.length);
      window.Plotly.react("plot-spectrum", [
        { type: "bar", x: orders(sb), y: sb, name: "before (θ = 0)", marker: { color: C_BEFORE },
          hovertemplate: "order %{x}<br>%{y:.3e} FS<extra>before</extra>" },
        { type: "bar", x: orders(sa), y: sa, name: "after (identified θ)", marker: { color: C_AFTER },
          hovertemplate: "order %{x}<br>%{y:.3e} FS<extra>after</extra>" },
      ], baseLayout("Fig. 10 — spectrum of α", "electrical order k (× f_e)", "amplitude |a_k| (FS, log)", {
        barmode: "group", bargap: 0.2, annotations,
        xaxis: { title: { text: "electrical order k (× f_e)" }, tickmode: "linear", dtick: n > 12 ? 2 : 1, range: [0.4, n + 0.6] },
        yaxis: { title: { text: "amplitude |a_k| (FS, log)" }, type: "log", exponentformat: "power" },
      }), PLOT_CONFIG);
    } else notes.push("no spectrum stored");

    const ab = tr.alpha_before || {};
    const aa = tr.alpha_after || {};
    const hasAlpha = Array.isArray(ab.alpha_fs) || Array.isArray(aa.alpha_fs);
    showFigure("plot-alpha", hasAlpha);
    if (hasAlpha) {
      window.Plotly.react("plot-alpha", [
        { x: ab.angle_rad || [], y: ab.alpha_fs || [], name: "before (θ = 0)", mode: "lines",
          line: { color: C_BEFORE, width: 1.2 }, hovertemplate: "φ_e %{x:.3f} rad<br>α %{y:.5f} FS<extra>before</extra>" },
        { x: aa.angle_rad || [], y: aa.alpha_fs || [], name: "after (identified θ)", mode: "lines",
          line: { color: C_AFTER, width: 1.2 }, hovertemplate: "φ_e %{x:.3f} rad<br>α %{y:.5f} FS<extra>after</extra>" },
      ], baseLayout("Fig. 10 — acceleration α, before / after", "electrical angle φ_e (rad, unwrapped)",
        "α (FS)"), PLOT_CONFIG);
    } else notes.push("no α snippets stored");

    // Fig. 8: grid-search surface (only for the grid method)
    const grid = Array.isArray(tr.grid) ? tr.grid : [];
    showFigure("plot-grid", grid.length > 0);
    if (grid.length > 0) drawGrid(r, grid, tr.grid_columns, d);

    setText("result-note", notes.length ? notes.join(" · ") : "");
  }

  function drawGrid(r, grid, cols, d) {
    const g = column(grid, cols, "gamma_deg", 0).map(Number);
    const dl = column(grid, cols, "delta_deg", 1).map(Number);
    const ac = column(grid, cols, "a_c", 2).map(Number);
    const as = column(grid, cols, "a_s", 3).map(Number);
    const xs = [...new Set(g)].sort((a, b) => a - b);
    const ys = [...new Set(dl)].sort((a, b) => a - b);
    const xi = new Map(xs.map((v, i) => [v, i]));
    const yi = new Map(ys.map((v, i) => [v, i]));
    const z = ys.map(() => xs.map(() => null));
    for (let k = 0; k < g.length; k++) z[yi.get(dl[k])][xi.get(g[k])] = Math.hypot(ac[k], as[k]);
    const traces = [{
      type: "contour", x: xs, y: ys, z, colorscale: "Viridis", connectgaps: false,
      contours: { coloring: "heatmap", showlines: true }, line: { width: 0.5, color: "rgba(255,255,255,0.45)" },
      colorbar: { title: { text: "|a_h| (FS)", side: "right" }, thickness: 12, len: 0.9 },
      hovertemplate: "γ %{x}°<br>δ %{y}°<br>|a_h| %{z:.3e} FS<extra></extra>", name: "|a_h|",
    }];
    const m = d.minimum;
    if (m && Number.isFinite(Number(m.gamma_deg))) {
      traces.push({ type: "scatter", mode: "markers", x: [m.gamma_deg], y: [m.delta_deg], name: "grid minimum",
        marker: { symbol: "x", size: 12, color: "#ffffff", line: { width: 1.5, color: "#1d2430" } },
        hovertemplate: "grid minimum<br>γ %{x:.3f}°<br>δ %{y:.2f}°<extra></extra>" });
    }
    const f = d.fit;
    if (f && Number.isFinite(Number(f.gamma_deg))) {
      traces.push({ type: "scatter", mode: "markers", x: [f.gamma_deg], y: [f.delta_deg], name: "affine fit",
        marker: { symbol: "star", size: 13, color: "#d1495b", line: { width: 1, color: "#ffffff" } },
        hovertemplate: "affine fit<br>γ %{x:.3f}°<br>δ %{y:.2f}°<extra></extra>" });
    }
    window.Plotly.react("plot-grid", traces, baseLayout(
      `Fig. 8 — grid search: |a_h| over (γ, δ), ${grid.length} points`, "injection amplitude γ (°)",
      "injection phase δ (°)", {
        legend: { orientation: "h", x: 0, xanchor: "left", y: -0.18, yanchor: "top", font: { size: 10 } },
        margin: { l: 64, r: 12, t: 36, b: 64 },
      }), PLOT_CONFIG);
  }

  // ---------------------------------------------------------------- wiring
  function init() {
    const tok = $("token");
    try {
      tok.value = localStorage.getItem(TOKEN_KEY) || "";
    } catch (_) { /* storage disabled */ }
    tok.addEventListener("input", () => {
      try {
        localStorage.setItem(TOKEN_KEY, tok.value.trim());
      } catch (_) { /* storage disabled */ }
    });
    $("sweep-form").addEventListener("submit", submitSweep);
    $("map-select").addEventListener("change", (e) => showMap(Number(e.target.value)));
    $("udc-select").addEventListener("change", drawMap);
    $("identify-form").addEventListener("submit", submitIdentify);
    $("identify-cancel").addEventListener("click", cancelJob);
    const method = $("identify-method");
    const setExample = () => { $("identify-options").placeholder = OPTION_EXAMPLES[method.value] || "{}"; };
    method.addEventListener("change", setExample);
    setExample();
    if (!window.Plotly) showMsg("map-note", ["Plotly.js did not load from /vendor/plotly.min.js — maps cannot be drawn."]);

    pollStatus();
    startEvents();
    loadSweeps();
    loadMaps(true);
    resumeJob();
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", init);
  else init();
})();
