// ripplecal dashboard: bench status (SSE with polling fallback), sweeps, compensation maps.
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
      if (p && p.kind === "sweep") scheduleSweepReload();
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
          text[i][j] = head + `<b>${p.sym} = ${Number(v).toFixed(p.digits)} ${p.unit === "deg" ? "°" : p.unit}</b>`;
        } else {
          text[i][j] = head + `<b>status: ${escapeHtml(String(c.status))}</b> (no value)`;
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
    }
  }

  function escapeHtml(s) {
    return s.replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" }[c]));
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
    if (!window.Plotly) showMsg("map-note", ["Plotly.js did not load from /vendor/plotly.min.js — maps cannot be drawn."]);

    pollStatus();
    startEvents();
    loadSweeps();
    loadMaps(true);
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", init);
  else init();
})();
