// Panel (2): start a sweep, list the sweeps with their progress, pause / resume / cancel them.
import * as api from "../api.js";
import { $, el, showMsg } from "../dom.js";
import { fmt, runLevel, shortTime } from "../format.js";

const RELOAD_DEBOUNCE_MS = 300;  // several events in a burst -> one GET /sweeps
const GRID_FIELDS = [["torque_nm", "torque"], ["speed_rpm", "speed"], ["udc_v", "DC link voltage"]];

const sweeps = new Map();        // id -> sweep object, as GET /sweeps answers
const lastPoint = new Map();     // sweep id -> text of its last finished point
let reloadTimer = null;
let openMap = () => {};

// openMapOf(mapId): what the "map N" link of a row does.
export function init({ openMapOf }) {
  openMap = openMapOf;
  $("sweep-form").addEventListener("submit", submit);
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

export function scheduleReload() {
  if (reloadTimer) return;
  reloadTimer = setTimeout(() => {
    reloadTimer = null;
    reload();
  }, RELOAD_DEBOUNCE_MS);
}

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
  $("sweep-empty").hidden = rows.length > 0;
  $("sweep-rows").replaceChildren(...rows.map(row));
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
  tr.appendChild(el("td", null, s.method || "—"));
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
  tr.appendChild(el("td", { class: "time" }, shortTime(s.created_at)));

  const act = el("td", { class: "actions" });
  const button = (label, action) => {
    const b = el("button", { type: "button", class: "small", "data-action": action }, label);
    b.addEventListener("click", () => control(s.id, action));
    act.appendChild(b);
  };
  if (s.state === "running" || s.state === "queued") button("pause", "pause");
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
  bar.appendChild(el("span", { class: "bar-text" }, `${done} / ${total}`));
  td.appendChild(bar);
  // outcomes apart: only ok cells go into a LUT
  const outcome = ["ok", "below_target", "no_authority", "failed"]
    .filter((k) => Number(prog[k]) > 0).map((k) => `${prog[k]} ${k.replace("_", " ")}`);
  if (outcome.length) td.appendChild(el("div", { class: "row-note", "data-testid": "sweep-outcome" }, outcome.join(" · ")));
  if (s.error) td.appendChild(el("div", { class: "row-error", "data-testid": "sweep-row-error" }, api.detailText(s.error)));
  else if (lastPoint.has(s.id) && (s.state === "running" || s.state === "paused")) {
    td.appendChild(el("div", { class: "row-note" }, lastPoint.get(s.id)));
  }
  return td;
}

// POST /sweeps/{id}/pause|resume|cancel
async function control(id, action) {
  showMsg("sweep-error", null);
  try {
    const s = await api.post(`/sweeps/${id}/${action}`);
    if (s && s.id !== undefined) sweeps.set(s.id, s);
    render();
    scheduleReload();
  } catch (e) {
    showMsg("sweep-error", api.errorLines(e), `${action} sweep ${id} failed (HTTP ${e.status || "?"})`);
  }
}

// "1, 2.5; 4" -> {vals: [1, 2.5, 4]} or {error}
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

async function submit(ev) {
  ev.preventDefault();
  showMsg("sweep-error", null);
  showMsg("sweep-ok", null);
  const f = ev.target;
  const grid = {};
  const errs = [];
  for (const [key, label] of GRID_FIELDS) {
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
    const s = await api.post("/sweeps", { grid, method: f.elements.method.value });
    if (s && s.id !== undefined) {
      sweeps.set(s.id, s);
      render();
      const n = s.progress && s.progress.total;
      showMsg("sweep-ok", [`Sweep ${s.id} accepted (${s.state}${n ? `, ${n} operating points` : ""}).`]);
    }
    scheduleReload();
  } catch (e) {
    showMsg("sweep-error", api.errorLines(e),
      e.status ? `Sweep rejected (HTTP ${e.status}):` : "Sweep request failed:");
  } finally {
    btn.disabled = false;
  }
}
