// Panel (3a): map b (picked here) against the map shown in the Map panel (a), from
// GET /maps/{a}/compare/{b}: |Δθ| and the suppression b's θ would reach on a's bench (predicted from
// a's measured S) as heatmaps at one DC-link voltage, and every matched cell in a table.
import * as api from "../api.js";
import { $, el, setText, showMsg } from "../dom.js";
import { fmt } from "../format.js";
import * as figures from "../figures.js";

const PLOT_DIV = { delta_theta_deg: "plot-compare-theta", predicted_suppression_db: "plot-compare-supp" };

let mapA = null;          // the id the Map panel shows
let comparison = null;    // the last answer of /compare
let asked = 0;            // a newer request wins over a late older answer

export function init() {
  $("compare-b").addEventListener("change", run);
  $("compare-udc").addEventListener("change", draw);
}

// The Map panel shows map `id` (main.js passes it on): it becomes map a.
export async function setMapA(id) {
  mapA = id;
  setText("compare-a", `a: map ${id}`);
  await reloadChoices();
  await run();
}

async function reloadChoices() {
  let maps;
  try {
    maps = await api.get("/maps");
  } catch (_) {
    return;
  }
  const sel = $("compare-b");
  const prev = sel.value;
  sel.replaceChildren(el("option", { value: "" }, "— pick map b —"),
    ...maps.slice().sort((x, y) => y.id - x.id).map((m) =>
      el("option", { value: String(m.id) }, `map ${m.id} · sweep ${m.sweep_id} · h=${m.harmonic_order}`)));
  if (maps.some((m) => String(m.id) === prev)) sel.value = prev;
}

function clear() {
  comparison = null;
  setText("compare-summary", "");
  $("compare-plots").hidden = true;
  $("compare-table").hidden = true;
  $("compare-rows").replaceChildren();
}

async function run() {
  const b = $("compare-b").value;
  const ask = ++asked;
  showMsg("compare-note", null);
  if (mapA === null || !b) {
    clear();
    return;
  }
  let answer;
  try {
    answer = await api.get(`/maps/${mapA}/compare/${b}`);
  } catch (e) {
    if (ask !== asked) return;
    clear();
    showMsg("compare-note", api.errorLines(e));
    return;
  }
  if (ask !== asked) return;
  comparison = answer;
  const s = answer.summary;
  const worst = s.worst_cell ? ` at ${fmt(s.worst_cell.torque_nm)} N·m / ${fmt(s.worst_cell.speed_rpm)} rpm` : "";
  setText("compare-summary", `${s.compared} cells compared · |Δθ| median ${fmt(s.median_delta_theta_deg, 2)}°, ` +
    `max ${fmt(s.max_delta_theta_deg, 2)}°${worst} · predicted suppression median ` +
    `${fmt(s.median_predicted_suppression_db, 1)} dB, worst ${fmt(s.min_predicted_suppression_db, 1)} dB`);
  const notes = [];
  if (!answer.same_axes) notes.push(`Different grids: compared where both have a cell; ${s.only_in_a} only in a, ${s.only_in_b} only in b.`);
  if (s.without_s) notes.push(`${s.without_s} cell(s) of map a stored no measured S: no prediction there.`);
  showMsg("compare-note", notes.length ? notes : null);
  const udcs = [...new Set(answer.cells.map((c) => Number(c.udc_v)))].sort((x, y) => x - y);
  const usel = $("compare-udc");
  const prev = usel.value;
  usel.replaceChildren(...udcs.map((u) => el("option", { value: String(u) }, `${u} V`)));
  if (udcs.some((u) => String(u) === prev)) usel.value = prev;
  $("compare-rows").replaceChildren(...answer.cells.map(row));
  $("compare-table").hidden = false;
  draw();
}

function row(c) {
  const tr = el("tr", { dataset: { testid: "compare-row", compared: c.compared ? "1" : "0" } });
  for (const [v, d] of [[c.torque_nm], [c.speed_rpm], [c.udc_v], [c.delta_gamma_deg, 2], [c.delta_delta_deg, 1],
    [c.delta_theta_deg, 2], [c.suppression_a_db, 1], [c.predicted_suppression_db, 1]]) {
    tr.appendChild(el("td", { class: "num" }, fmt(v, d)));
  }
  tr.appendChild(el("td", null, c.note || ""));
  return tr;
}

function draw() {
  if (!comparison || !figures.plotlyLoaded() || comparison.cells.length === 0) {
    $("compare-plots").hidden = true;
    return;
  }
  $("compare-plots").hidden = false;
  const slice = figures.mapSlice({ cells: figures.compareCells(comparison) }, Number($("compare-udc").value));
  for (const q of figures.COMPARE_QUANTITIES) figures.draw(PLOT_DIV[q.key], figures.mapHeatmap(slice, q));
}
