// Panel (2): preview and start a sweep, list the sweeps with their progress, pause / resume / cancel them.
import * as api from "../api.js";
import { coalesced } from "../coalesce.js";
import { $, el, showMsg } from "../dom.js";
import { fmt, runLevel, shortTime } from "../format.js";
import { submittedSweep } from "../grid-form.js";
import * as benchChoice from "../bench-choice.js";

const RELOAD_DEBOUNCE_MS = 300;  // several events in a burst -> one GET /sweeps
const sweeps = new Map();        // id -> sweep object, as GET /sweeps answers
const lastPoint = new Map();     // sweep id -> text of its last finished point
const pausing = new Set();       // sweep ids paused by us while their point in flight finishes
const attention = new Map();     // sweep id -> {key, points}: its non-ok points with their reasons
const attentionOpen = new Set(); // sweep ids whose list the reader opened
const NOT_OK = ["failed", "below_target", "no_authority"];
let openMap = () => {};

// openMapOf(mapId): what the "map N" link of a row does.
export function init({ openMapOf }) {
  openMap = openMapOf;
  $("sweep-form").addEventListener("submit", submit);
  $("sweep-preview-btn").addEventListener("click", preview);
  // a preview shown for other inputs would mislead: it is marked until previewed again
  $("sweep-form").addEventListener("input", () => {
    const box = $("sweep-preview");
    if (box.hidden) return;
    box.dataset.stale = "1";
    box.style.opacity = "0.55";
    box.title = "the form changed since this preview: preview again";
  });
}

export async function reload() {
  try {
    const list = await api.get("/sweeps");
    sweeps.clear();
    for (const s of list) sweeps.set(s.id, s);
    render();
  } catch (_) {
    /* shown by the live indicator; keep the last list */
  }
}

export const scheduleReload = coalesced(() => reload(), RELOAD_DEBOUNCE_MS);

// SSE sweep.progress {sweep_id, state, done, total, map_id}
export function onProgress(p) {
  const s = sweeps.get(p.sweep_id);
  if (!s) {
    scheduleReload();
    return;
  }
  s.state = p.state || s.state;
  s.progress = { done: p.done, total: p.total };
  if (p.map_id !== undefined && p.map_id !== null) s.map_id = p.map_id;
  render();
  if (["done", "failed", "cancelled"].includes(p.state)) scheduleReload();
}

// SSE sweep.point {sweep_id, operating_point, state, result}
export function onPoint(p) {
  const op = p.operating_point || {};
  const r = p.result || {};
  let text = `last: T ${fmt(op.torque_nm)} N·m, n ${fmt(op.speed_rpm)} rpm, U ${fmt(op.udc_v)} V — ${p.state}`;
  if (p.result) {
    text += `, γ ${fmt(r.gamma_deg, 2)}°, δ ${fmt(r.delta_deg, 1)}°`;
    if (r.suppression_db !== undefined && r.suppression_db !== null) text += `, ${fmt(r.suppression_db, 1)} dB`;
  }
  lastPoint.set(p.sweep_id, text);
  if (sweeps.has(p.sweep_id)) render();
}

// SSE job.state {job_id, state, kind}: a sweep's job changed, so its row may have.
export function onJobState(p) {
  if (p.kind === "sweep") scheduleReload();
}

function render() {
  const rows = [...sweeps.values()].sort((a, b) => b.id - a.id);
  for (const s of rows) if (s.state !== "running" && s.state !== "queued") pausing.delete(s.id);
  $("sweep-empty").hidden = rows.length > 0;
  $("sweep-rows").replaceChildren(...rows.map(row));
  for (const s of rows) loadAttention(s);
}

// Every second (main.js): elapsed time and ETA of the running sweeps count on.
export function tick() {
  for (const s of sweeps.values()) {
    if (s.state !== "running") continue;
    const cell = document.querySelector(`[data-sweep-id="${s.id}"] [data-testid="sweep-timing"]`);
    if (cell) cell.textContent = timingText(s);
  }
}

function seconds(iso) {
  const t = Date.parse(iso);
  return Number.isFinite(t) ? t / 1000 : null;
}

export function duration(sec) {
  if (sec === null || !Number.isFinite(sec)) return "—";
  const s = Math.max(0, Math.round(sec));
  if (s < 60) return `${s} s`;
  if (s < 3600) return `${Math.floor(s / 60)} min ${String(s % 60).padStart(2, "0")} s`;
  return `${Math.floor(s / 3600)} h ${String(Math.floor((s % 3600) / 60)).padStart(2, "0")} min`;
}

// "elapsed 2 min 10 s · ETA 4 min 20 s" (ETA from the mean time per point so far; running sweeps only)
function timingText(s) {
  const start = seconds(s.started_at);
  if (start === null) return "";
  const end = s.finished_at ? seconds(s.finished_at) : Date.now() / 1000;
  const elapsed = end - start;
  let text = `elapsed ${duration(elapsed)}`;
  const prog = s.progress || {};
  const done = Number(prog.done) || 0;
  const total = Number(prog.total) || 0;
  if (s.state === "running") {
    text += done > 0 && total > done ? ` · ETA ${duration((elapsed / done) * (total - done))}` : done === 0 ? " · ETA after the first point" : "";
  }
  return text;
}

// The sweep's non-ok points with their reasons (GET /sweeps/{id}), fetched again only when its counts or
// its plant time change (a second pass replaces a point's result without changing the counts).
async function loadAttention(s) {
  const prog = s.progress || {};
  const bad = NOT_OK.reduce((n, k) => n + (Number(prog[k]) || 0), 0);
  const key = `${prog.done}/${bad}/${s.plant_time_s}`;
  if (bad === 0 || (attention.has(s.id) && attention.get(s.id).key === key)) return;
  attention.set(s.id, { key, points: attention.has(s.id) ? attention.get(s.id).points : [] });
  try {
    const full = await api.get(`/sweeps/${s.id}`);
    // an answer to an older request must not overwrite a newer one (requests can overtake)
    if (!attention.has(s.id) || attention.get(s.id).key !== key) return;
    const points = (full.points || []).filter((p) => NOT_OK.includes(p.state));
    attention.set(s.id, { key, points });
    const cell = document.querySelector(`[data-sweep-id="${s.id}"] .wide`);
    if (cell) renderAttention(cell, s.id);
  } catch (_) {
    attention.delete(s.id);   /* retried on the next render */
  }
}

function renderAttention(td, id) {
  const old = td.querySelector('[data-testid="sweep-attention"]');
  if (old) old.remove();
  const a = attention.get(id);
  if (!a || a.points.length === 0) return;
  const box = el("details", { class: "attention", "data-testid": "sweep-attention" });
  box.open = attentionOpen.has(id);      // rows are redrawn on every event: keep what the reader opened
  box.addEventListener("toggle", () => (box.open ? attentionOpen.add(id) : attentionOpen.delete(id)));
  box.appendChild(el("summary", null, `${a.points.length} point${a.points.length > 1 ? "s" : ""} not ok — reasons`));
  const ul = el("ul");
  for (const p of a.points) {
    const op = p.operating_point || {};
    const r = p.result || {};
    const reason = p.error || r.message || "no reason stored";
    const li = el("li", { "data-testid": "sweep-attention-point", "data-status": p.state });
    li.appendChild(el("span", { class: "badge", "data-level": p.state === "failed" ? "bad" : "warn" }, p.state));
    li.appendChild(document.createTextNode(
      ` T ${fmt(op.torque_nm)} N·m, n ${fmt(op.speed_rpm)} rpm, U ${fmt(op.udc_v)} V: ${api.detailText(reason)}`));
    ul.appendChild(li);
  }
  box.appendChild(ul);
  td.appendChild(box);
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

function row(s) {
  const tr = el("tr", { "data-testid": "sweep-row", "data-sweep-id": String(s.id), "data-state": s.state });
  tr.appendChild(el("td", { class: "num" }, String(s.id)));
  tr.appendChild(el("td", null)).appendChild(el("span", { class: "badge", "data-level": runLevel(s.state),
    "data-testid": "sweep-state" }, s.state));
  // a refinement is listed as what the user started (refine on the map panel), its cells' method beneath
  const kindTd = tr.appendChild(el("td", { "data-testid": "sweep-kind", "data-kind": s.kind || "sweep" }));
  if (s.kind === "refinement") {
    kindTd.appendChild(el("div", null, `refinement of map ${s.source_map_id ?? "—"}`));
    kindTd.appendChild(el("div", { class: "row-note" }, `cells by ${s.method || "—"}`));
  } else kindTd.textContent = s.method || "—";
  tr.appendChild(el("td", { class: "grid-cell", title: gridFull(s.grid) }, gridSummary(s.grid)));
  tr.appendChild(progressCell(s));

  const mapTd = el("td", { class: "map-cell" });
  if (s.map_id !== null && s.map_id !== undefined) {
    const a = el("a", { href: "#map" }, `map ${s.map_id}`);
    a.addEventListener("click", (ev) => {
      ev.preventDefault();
      openMap(s.map_id);
    });
    mapTd.appendChild(a);
  } else mapTd.textContent = "—";
  tr.appendChild(mapTd);
  // date over time: the column stays narrow
  const [day, clock] = shortTime(s.created_at).split(" ");
  const timeTd = el("td", { class: "time", title: s.created_at || "" }, day || "—");
  if (clock) timeTd.appendChild(el("div", null, clock));
  tr.appendChild(timeTd);

  const act = el("td", { class: "actions" });
  const button = (label, action) => {
    const b = el("button", { type: "button", class: "small", "data-action": action }, label);
    b.addEventListener("click", () => control(s.id, action));
    act.appendChild(b);
  };
  if (pausing.has(s.id) && (s.state === "running" || s.state === "queued")) {
    act.appendChild(el("span", { class: "badge", "data-level": "warn", "data-testid": "sweep-pausing" }, "pausing…"));
  } else if (s.state === "running" || s.state === "queued") button("pause", "pause");
  if (s.state === "paused") button("resume", "resume");
  if (s.state === "running" || s.state === "queued" || s.state === "paused") button("cancel", "cancel");
  tr.appendChild(act);
  return tr;
}

function progressCell(s) {
  const td = el("td", { class: "wide" });
  const prog = s.progress || {};
  const done = Number(prog.done) || 0;
  const total = Number(prog.total) || 0;
  const bar = el("div", { class: "bar", "data-testid": "sweep-progress", "data-level": runLevel(s.state) });
  const fill = el("div", { class: "fill" });
  fill.style.width = total ? `${Math.min(100, (100 * done) / total).toFixed(1)}%` : "0%";
  bar.appendChild(fill);
  bar.appendChild(el("span", { class: "bar-text" }, `${done} / ${total}` + (s.refinement ? " cells" : "")));
  td.appendChild(bar);
  if (s.refinement) {  // its cells are planned round by round: the bar counts those planned so far
    const ref = s.refinement;
    td.appendChild(el("div", { class: "row-note", "data-testid": "sweep-refinement" },
      `${ref.rounds.length} round(s) validated · ${ref.phase} · ${ref.cells_added} of max ${ref.max_cells} cells identified`));
  }
  // outcomes apart: only ok cells go into a LUT
  const outcome = ["ok", "below_target", "no_authority", "failed"]
    .filter((k) => Number(prog[k]) > 0).map((k) => `${prog[k]} ${k.replace("_", " ")}`);
  if (outcome.length) td.appendChild(el("div", { class: "row-note", "data-testid": "sweep-outcome" }, outcome.join(" · ")));
  const timing = timingText(s);
  if (timing) td.appendChild(el("div", { class: "row-note", "data-testid": "sweep-timing" }, timing));
  if (s.waiting_for) {
    td.appendChild(el("div", { class: "row-note", "data-testid": "sweep-waiting-for" }, `waits for ${s.waiting_for}`));
  }
  if (s.control_request) {  // asked here, done by the service of the sweep's bench within about a second
    td.appendChild(el("div", { class: "row-note", "data-testid": "sweep-control-request" },
      `${s.control_request} asked of bench ${s.bench}'s service`));
  }
  if (s.control_note) td.appendChild(el("div", { class: "row-error", "data-testid": "sweep-control-note" }, s.control_note));
  if (s.state === "paused" && s.pause_reason) {
    td.appendChild(el("div", { class: "row-note", "data-testid": "sweep-pause-reason" }, `paused: ${s.pause_reason}`));
  }
  if (s.error) td.appendChild(el("div", { class: "row-error", "data-testid": "sweep-row-error" }, api.detailText(s.error)));
  else if (lastPoint.has(s.id) && (s.state === "running" || s.state === "paused")) {
    td.appendChild(el("div", { class: "row-note" }, lastPoint.get(s.id)));
  }
  renderAttention(td, s.id);
  return td;
}

// POST /sweeps/{id}/pause|resume|cancel
async function control(id, action) {
  showMsg("sweep-error", null);
  // the point in flight finishes first: say so at once instead of a button that seems to do nothing
  if (action === "pause") {
    pausing.add(id);
    render();
  }
  try {
    const s = await api.post(`/sweeps/${id}/${action}`);
    if (s && s.id !== undefined) sweeps.set(s.id, s);
    render();
    scheduleReload();
  } catch (e) {
    pausing.delete(id);
    render();
    showMsg("sweep-error", api.errorLines(e), `${action} sweep ${id} failed (HTTP ${e.status || "?"})`);
  }
}

// The request both Preview and Start send: the same body, so the sweep started is the plan previewed.
function sweepRequest(f) {
  const sweep = submittedSweep(f, "sweep-error", "sweep-ok");
  if (!sweep) return null;
  const body = { grid: sweep.grid, method: f.elements.method.value };
  if (sweep.regime) body.regime = sweep.regime;
  return body;
}

// POST /sweeps/preview (no token, nothing queued): point count, the speed axis with the values the plan
// added, the predicted field-weakening onset per torque, what POST /sweeps would refuse, the estimate.
async function preview() {
  const body = sweepRequest($("sweep-form"));
  if (!body) return;
  const btn = $("sweep-preview-btn");
  btn.disabled = true;
  try {
    renderPreview(await api.post("/sweeps/preview", body));
  } catch (e) {
    $("sweep-preview").hidden = true;
    showMsg("sweep-error", api.errorLines(e),
      e.status ? `Preview refused (HTTP ${e.status}):` : "Preview request failed:");
  } finally {
    btn.disabled = false;
  }
}

function renderPreview(p) {
  const box = $("sweep-preview");
  delete box.dataset.stale;
  box.style.opacity = "";
  box.title = "";
  box.dataset.accepted = p.accepted ? "1" : "0";
  const added = p.added_speeds_rpm || [];
  const req = p.requested_grid || {};
  const requested = (req.torque_nm || []).length * (req.speed_rpm || []).length * (req.udc_v || []).length;
  let summary = `${p.total} operating point${p.total === 1 ? "" : "s"}`;
  if (added.length) summary += ` (${requested} requested; ${added.length} speed value${added.length > 1 ? "s" : ""} added around the onset)`;
  summary += p.accepted ? " · Start sweep would queue it" : " · Start sweep would be refused:";
  $("sweep-preview-summary").textContent = summary;

  const axis = $("sweep-preview-axis");
  axis.replaceChildren();
  (p.speed_axis || []).forEach((v, i) => {
    if (i) axis.appendChild(document.createTextNode(", "));
    const why = (v.reasons || []).join("\n");
    const e = el(v.added ? "strong" : "span", { "data-testid": "sweep-preview-speed", "data-added": v.added ? "1" : "0",
      "data-speed": String(v.speed_rpm) }, fmt(v.speed_rpm) + (v.added ? "+" : ""));
    if (why) e.title = why;
    axis.appendChild(e);
  });

  const several = new Set((p.onsets || []).map((o) => o.udc_v)).size > 1;
  const onsets = $("sweep-preview-onsets");
  onsets.replaceChildren();
  (p.onsets || []).forEach((o, i) => {
    if (i) onsets.appendChild(document.createTextNode(" · "));
    const at = o.onset_rpm === null || o.onset_rpm === undefined ? "none" : `${fmt(o.onset_rpm, 0)} rpm`;
    const e = el("span", { "data-testid": "sweep-preview-onset", style: "white-space: nowrap", "data-torque": String(o.torque_nm),
      "data-udc": String(o.udc_v), "data-onset": o.onset_rpm === null ? "" : String(o.onset_rpm) },
      `${fmt(o.torque_nm)} N·m${several ? ` @ ${fmt(o.udc_v)} V` : ""}: ${at}`);
    if (o.note) e.title = o.note;
    onsets.appendChild(e);
  });
  $("sweep-preview-margin").textContent = fmt(p.voltage_margin);

  const est = p.estimate;
  $("sweep-preview-estimate").textContent = est
    ? `Estimated bench time ≈ ${duration(est.estimated_s)} (worst case ${duration(est.worst_case_s)}); ${est.basis}.`
    : "No estimate: the grid cannot be planned.";

  // points the envelope model of the motor settings refuses: stored failed with the reason, never run
  const notRun = $("sweep-preview-not-run");
  const outside = p.not_run || [];
  notRun.hidden = !outside.length;
  notRun.textContent = outside.length
    ? `${outside.length} point${outside.length > 1 ? "s" : ""} outside the envelope of the motor settings, not run: ` +
      outside.slice(0, 6).map((c) => `${fmt(c.operating_point.torque_nm)} N·m @ ${fmt(c.operating_point.speed_rpm)} rpm`).join(", ") +
      (outside.length > 6 ? ", …" : "")
    : "";
  notRun.title = outside.map((c) => c.reason).slice(0, 6).join("\n");

  const problems = $("sweep-preview-problems");
  problems.replaceChildren();
  problems.hidden = p.accepted;
  if (!p.accepted) {
    const ul = el("ul");
    for (const d of p.problems || []) {
      const loc = Array.isArray(d.loc) ? d.loc.filter((x) => x !== "body").join(".") : "";
      ul.appendChild(el("li", null, (loc ? loc + ": " : "") + (d.msg || JSON.stringify(d))));
    }
    problems.appendChild(ul);
  }
  box.hidden = false;
}

async function submit(ev) {
  ev.preventDefault();
  const f = ev.target;
  const body = sweepRequest(f);
  if (!body) return;
  const btn = $("sweep-submit");
  btn.disabled = true;
  try {
    const s = await api.post("/sweeps", benchChoice.withBench(body));
    if (s && s.id !== undefined) {
      sweeps.set(s.id, s);
      render();
      const n = s.progress && s.progress.total;
      showMsg("sweep-ok", [`Sweep ${s.id} accepted (${s.state}${n ? `, ${n} operating points` : ""})`
        + (s.waiting_for ? `; it waits for ${s.waiting_for}.` : ".")]);
    }
    scheduleReload();
  } catch (e) {
    showMsg("sweep-error", api.errorLines(e),
      e.status ? `Sweep rejected (HTTP ${e.status}):` : "Sweep request failed:");
  } finally {
    btn.disabled = false;
  }
}
