// Panel (3): the compensation maps: pick a map and a DC-link voltage, see gamma, delta and the
// suppression as heatmaps (each axis at its real breakpoints; filled cells hatched, their fill's
// source in the hover), export the LUT; a click on a cell opens its stored result.
import * as api from "../api.js";
import { $, el, setText, showMsg } from "../dom.js";
import { fmt, shortTime } from "../format.js";
import * as figures from "../figures.js";

// where each quantity of figures.MAP_QUANTITIES is drawn
const PLOT_DIV = { gamma_deg: "plot-gamma", delta_deg: "plot-delta", suppression_db: "plot-supp" };

let currentMap = null;           // the full map shown, as GET /maps/{id} answers
let openResult = () => {};
let mapShown = () => {};
let onShown = () => {};

// openResultOf(resultId, source): what a click on a map cell does; onMapShown(id): a map is shown;
// shown(map, udc): the map and U_dc slice drawn (the validation panel follows it).
export function init({ openResultOf, onMapShown, shown }) {
  openResult = openResultOf;
  if (onMapShown) mapShown = onMapShown;
  if (shown) onShown = shown;
  $("map-select").addEventListener("change", (e) => show(Number(e.target.value)));
  // another part of the map card asks for a map (e.g. a refinement's): detail = its id
  $("map-select").addEventListener("open-map", (e) => select(Number(e.detail)));
  $("udc-select").addEventListener("change", draw);
  $("order-select").addEventListener("change", draw);
  if (!figures.plotlyLoaded()) {
    showMsg("map-note", ["Plotly.js did not load from /vendor/plotly.min.js — maps cannot be drawn."]);
  }
}

// Refill the map list; show the newest map, or keep the one selected if it is still there.
export async function reload(selectNewest) {
  let maps;
  let sweeps;
  try {
    // the sweeps say which maps a refinement made (kind refinement: its source map)
    [maps, sweeps] = await Promise.all([api.get("/maps"), api.get("/sweeps").catch(() => [])]);
  } catch (_) {
    return;
  }
  const refinedFrom = new Map(sweeps.filter((s) => s.kind === "refinement" && s.refinement)
    .map((s) => [s.id, s.refinement.source_map_id]));
  const sel = $("map-select");
  const prev = sel.value;
  sel.replaceChildren(...maps.slice().sort((a, b) => b.id - a.id).map((m) => {
    const from = refinedFrom.get(m.sweep_id);
    const origin = from === undefined ? `sweep ${m.sweep_id}` : `refined from ${from} (refinement ${m.sweep_id})`;
    return el("option", { value: String(m.id), dataset: from === undefined ? {} : { refinedFrom: String(from) } },
      `map ${m.id} · ${origin} · h=${m.harmonic_order} · ${shortTime(m.created_at)}`);
  }));
  $("map-empty").hidden = maps.length > 0;
  $("map").dataset.empty = maps.length === 0 ? "1" : "";
  if (maps.length === 0) return;
  if (!selectNewest && prev && maps.some((m) => String(m.id) === prev)) {
    sel.value = prev;
  } else {
    sel.value = sel.options[0].value;
    await show(Number(sel.value));
  }
}

export async function select(id) {
  const sel = $("map-select");
  if (![...sel.options].some((o) => o.value === String(id))) await reload(false);
  sel.value = String(id);
  await show(id);
}

// SSE sweep.progress: a finished sweep brings its map to the front; a refinement (a sweep of kind refinement,
// started from this panel) is named as what it is, with the map it refined.
export async function onSweepProgress(p) {
  if (p.state !== "done" || p.map_id === null || p.map_id === undefined) return;
  await reload(false);
  select(p.map_id);  // clears the note at once, then fetches; the note below stays
  showMsg("map-note", [p.kind === "refinement" ?
    `Refinement ${p.sweep_id} finished — showing its refined map ${p.map_id}.` :
    `Sweep ${p.sweep_id} finished — showing its map ${p.map_id}.`]);
}

async function show(id) {
  showMsg("map-note", null);
  for (const a of document.querySelectorAll("#map-exports a")) {
    a.href = `${api.API_BASE}/maps/${id}/export?format=${a.dataset.format}`;
    a.setAttribute("download", "");
  }
  let m;
  try {
    m = await api.get(`/maps/${id}`);
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
  // a map of several orders: one heat map set per order, chosen here (the map's own order first)
  const orders = m.orders && m.orders.length ? m.orders : [m.harmonic_order];
  $("order-select").replaceChildren(...orders.map((h) => el("option", { value: String(h) }, `${h}th`)));
  $("order-choice").hidden = orders.length < 2;
  const counts = {};
  for (const c of m.cells) counts[c.status] = (counts[c.status] || 0) + 1;
  const countText = Object.entries(counts).map(([k, v]) => `${v} ${k}`).join(", ");
  const q = m.quality || {};
  // filled: not ok, but carrying a fill (service/maps/fill.py) the LUT takes with "with fill"
  const filled = m.cells.filter((c) => c.status !== "ok" && c.filled).length;
  $("map-meta").dataset.filled = String(filled);
  const prov = m.provenance || {};
  const origin = m.refined_from ? `refined from ${m.refined_from} (refinement ${prov.refinement_id ?? m.sweep_id}, ` +
    `round ${prov.round ?? "—"}, ${prov.cells_added ?? "—"} cells identified)` : `sweep ${m.sweep_id}`;
  $("map-meta").dataset.refinedFrom = m.refined_from ? String(m.refined_from) : "";
  const further = (m.further_orders || []).map((o) =>
    ` · order ${o.order}: ${o.status_counts.ok || 0} ok of ${o.cells.length}, ${o.filled_cells} filled`).join("");
  setText("map-meta", `h = ${orders.join(" + ")} · method ${m.method || "—"} · ${origin} · ` +
    `sw ${m.software_version || "—"} · ${m.cells.length} cells (${countText}) · ${filled} filled · ` +
    `${q.outliers || 0} outlier(s)${further}`);
  // outliers (ringed in the plots) with the reason to act on
  const outliers = m.cells.filter((c) => c.quality === "outlier").map((c) =>
    `T* ${fmt(c.torque_nm)} N·m, n ${fmt(c.speed_rpm)} rpm, U_dc ${fmt(c.udc_v)} V: ${c.outlier_reason}`);
  showMsg("map-quality", outliers.length ? outliers : null, outliers.length ? "Outliers against their neighbours" : undefined);
  // a cancelled sweep's map: say it is partial, before anyone downloads it
  if (m.partial) showMsg("map-note", [m.partial], "Partial map");
  draw();
  mapShown(id);
}

function draw() {
  if (currentMap) onShown(currentMap, Number($("udc-select").value));
  if (!figures.plotlyLoaded() || !currentMap) return;
  const slice = figures.mapSlice(orderShown(), Number($("udc-select").value));
  // several orders: each heat map says whose it is
  if ((currentMap.orders || []).length > 1) slice.orderLabel = `order ${$("order-select").value} · `;
  for (const q of figures.MAP_QUANTITIES) {
    const div = PLOT_DIV[q.key];
    figures.draw(div, figures.mapHeatmap(slice, q));
    figures.onClick(div, openCell);
  }
}

// the map as the chosen order's: a further order's cells in place of the map's own
function orderShown() {
  const order = Number($("order-select").value);
  const further = (currentMap.further_orders || []).find((o) => o.order === order);
  return further ? { ...currentMap, harmonic_order: order, cells: further.cells } : currentMap;
}

function openCell(pt) {
  if (!currentMap) return;
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
}
