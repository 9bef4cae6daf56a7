// Panel (3b): the map shown, validated in the drive's own LUT mode: "Validate on drive" (operator)
// starts the job (POST /maps/{id}/validate); the latest validation is drawn as a heat map of the
// suppression over the finer grid (grid points and the midpoints between them) at the U_dc chosen
// in the map panel, with its summary (grid / midpoint median and minimum, the worst cell). Its
// "Refine on drive" part is map-refine.js, which this module hands the map shown and the live events.
import * as api from "../api.js";
import { $, setText, showMsg } from "../dom.js";
import { fmt, shortTime } from "../format.js";
import * as figures from "../figures.js";
import * as events from "../events.js";
import * as refine from "./map-refine.js";
import * as benchChoice from "../bench-choice.js";

let mapId = null;            // the map the map panel shows
let udc = null;              // its U_dc slice
let validation = null;       // GET /maps/{id}/validation of that map, or null
let runningJob = null;       // the validation job this page started

export function init() {
  $("validate-btn").addEventListener("click", start);
  // (main.js wires the other panels; the refinement's events and "open a map" come through here)
  refine.init({
    subscribe: events.on,
    openMapInView: (id) => $("map-select").dispatchEvent(new CustomEvent("open-map", { detail: id })),
  });
}

// The map panel shows map `m` at `udcV`: fetch its latest validation (if any) and draw it.
export async function show(m, udcV) {
  const changed = !m || m.id !== mapId || !validation || !m.validation || m.validation.id !== validation.id;
  mapId = m ? m.id : null;
  udc = udcV;
  refine.show(m, udcV);
  $("validate-btn").disabled = mapId === null;
  if (!changed) return draw();
  validation = null;
  if (m && m.validation) {
    try {
      validation = await api.get(`/maps/${m.id}/validation`);
    } catch (e) {
      showMsg("validation-note", [`validation of map ${m.id}: ${e.message}`]);
    }
  }
  draw();
}

async function start() {
  if (mapId === null) return;
  showMsg("validation-note", null);
  try {
    const job = await api.post(`/maps/${mapId}/validate`, benchChoice.withBench({ force: $("validate-force").checked }));
    runningJob = job.id;
    showMsg("validation-note", [`Validation job ${job.id} queued: LUT download, then every grid point and midpoint ` +
      "in the drive's LUT mode."]);
  } catch (e) {
    showMsg("validation-note", api.errorLines(e), "Validation refused");
  }
}

// SSE job.state: a validation job that ended brings its result in (a refinement's too: it validates).
export async function onJobState(p) {
  if (!["validation", "refinement"].includes(p.kind) || ["queued", "running"].includes(p.state)) return;
  if (p.kind === "validation" && p.job_id === runningJob) {
    runningJob = null;
    showMsg("validation-note", p.state === "done" ? null :
      [`Validation job ${p.job_id} ${p.state}${p.error ? ": " + p.error : ""}`]);
  }
  if (mapId === null) return;
  try {
    const m = await api.get(`/maps/${mapId}`);
    validation = null;
    await show(m, udc);
  } catch (_) { /* the next map refresh brings it */ }
}

function summaryText(v) {
  const part = (name, k) => (k.median_db === null || k.median_db === undefined ? `${name}: none measured` :
    `${name} median ${fmt(k.median_db, 1)} dB, min ${fmt(k.min_db, 1)} dB (${k.measured}/${k.cells})`);
  const w = v.worst;
  const worst = w ? ` · worst ${fmt(w.suppression_db, 1)} dB at ${fmt(w.operating_point.torque_nm)} N·m, ` +
    `${fmt(w.operating_point.speed_rpm)} rpm (${w.kind})` : "";
  return `job ${v.job_id} · ${v.state} · ${shortTime(v.finished_at)} · ${part("grid", v.grid)} · ` +
    `${part("midpoints", v.midpoint)}${worst}` + (v.error ? ` · ${v.error}` : "");
}

function draw() {
  const box = $("map-validation");
  box.dataset.validated = validation ? "1" : "";
  if (!validation) {
    setText("validation-meta", mapId === null ? "" : "Not validated in the drive's LUT mode yet.");
    figures.purge("plot-validation");
    return;
  }
  setText("validation-meta", summaryText(validation));
  if (figures.plotlyLoaded() && udc !== null) {
    figures.draw("plot-validation", figures.validationHeatmap(validation.cells, udc));
  }
}
