// Part of the map panel's validation card (map-validation.js hands it the map shown and the events):
// "Refine on drive" (operator) refines the shown map (POST /maps/{id}/refine: validate it in the drive's
// LUT mode, insert axis values where a point misses the target, identify the new cells, validate again).
// While it runs: the round, its phase (measuring N cells / validating map M: k of n points) and the
// cells identified of the budget, from SSE (refinement.progress, job.progress, sweep.point, sweep.progress)
// and GET /jobs/{id} at 1 Hz so a lost event never stalls it. Then the outcome, a table of the rounds,
// and the source map's validation beside the refined map's (same colour scale, real axis positions).
import * as api from "../api.js";
import { $, el, setText, showMsg } from "../dom.js";
import { fmt } from "../format.js";
import * as figures from "../figures.js";
import { coalesced } from "../coalesce.js";
import * as benchChoice from "../bench-choice.js";

const POLL_MS = 1000;
const ACTIVE = ["queued", "running", "paused", "interrupted"];   // the refinement's (its sweep's) states

let openMap = () => {};
let mapId = null;           // the map the map panel shows: what the button refines
let udc = null;             // its U_dc slice
let run = null;             // the refinement followed (see fresh())
let pollTimer = null;

// subscribe(type, fn): the live events; openMapInView(id): show a map in the map panel.
export function init({ subscribe, openMapInView }) {
  openMap = openMapInView;
  $("refine-btn").addEventListener("click", start);
  $("refine-cancel").addEventListener("click", () => control("cancel"));
  $("refine-resume").addEventListener("click", () => control("resume"));
  subscribe("refinement.progress", onRefinementProgress);
  subscribe("job.progress", onJobProgress);
  subscribe("sweep.point", onSweepPoint);
  subscribe("sweep.progress", onSweepProgress);
  subscribe("job.state", onJobState);
}

function fresh(sweepId, jobId) {
  return {
    sweepId, jobId, refinement: null, state: "queued", error: null, pauseReason: null,
    live: { round: 0, phase: "", what: "", toMeasure: null, measured: 0, validated: new Set(), total: null },
    roundsSeen: -1, source: null, refined: null,
  };
}

// running (or not yet read): until the job's own answer says it ended, whatever an event said first
const active = () => run !== null &&
  (ACTIVE.includes(run.state) || !run.refinement || ACTIVE.includes(run.refinement.state));

// The map panel shows map `m` at `udcV`. A refined map brings its refinement in (when none runs);
// a map that is no part of the refinement shown clears it.
export function show(m, udcV) {
  mapId = m ? m.id : null;
  udc = udcV;
  $("refine-btn").disabled = mapId === null || active();
  if (!active() && m) {
    const prov = m.provenance || {};
    if (m.refined_from && prov.refinement_id && (!run || run.sweepId !== prov.refinement_id)) {
      follow(fresh(prov.refinement_id, null));
      return;
    }
    if (run && !belongs(m.id)) {
      run = null;
      render();
      return;
    }
  }
  drawPlots();
}

function belongs(id) {
  const r = run && run.refinement;
  return Boolean(r) && (r.source_map_id === id || r.map_id === id || r.rounds.some((x) => x.map_id === id));
}

async function start() {
  if (mapId === null || active()) return;
  showMsg("refine-note", null);
  const target = Number($("refine-target").value);
  const maxCells = Number($("refine-max-cells").value);
  const maxBytes = Number($("refine-max-bytes").value);
  if (!Number.isFinite(target) || !Number.isInteger(maxCells) || !Number.isInteger(maxBytes)) {
    showMsg("refine-note", ["target (dB), max cells and max bytes (whole numbers) are needed"], "Refinement not started");
    return;
  }
  const body = { target_db: target, max_cells: maxCells, max_bytes: maxBytes, lut_cells: $("refine-lut-cells").value };
  if ($("refine-runups").checked) body.validation = { runups: true, runup_torques_max: 7 };
  const source = mapId;
  $("refine-btn").disabled = true;
  try {
    const job = await api.post(`/maps/${source}/refine`, benchChoice.withBench(body));
    const r = fresh(job.sweep_id, job.id);
    take(r, job.result, job.state === "queued" ? "queued" : (job.result || {}).state, job.error);
    // "submitted", not "queued": the line below says its state as it changes (queued, running, done)
    showMsg("refine-note", [`Refinement ${job.sweep_id} of map ${source} submitted (job ${job.id}): target ` +
      `${fmt(target)} dB at every grid point and midpoint, at most ${maxCells} cell(s) identified (new and re-measured).`]);
    r.queuedNote = true;
    follow(r);
  } catch (e) {
    $("refine-btn").disabled = mapId === null || active();
    showMsg("refine-note", api.errorLines(e), "Refinement refused");
  }
}

function follow(r) {
  run = r;
  render();
  refreshSoon();
  if (!pollTimer) pollTimer = setInterval(poll, POLL_MS);
}

function poll() {
  if (active()) {
    refresh();
  } else {
    clearInterval(pollTimer);
    pollTimer = null;
  }
}

async function control(action) {
  if (!run) return;
  try {
    await api.post(`/sweeps/${run.sweepId}/${action}`);
  } catch (e) {
    run.queuedNote = false;
    showMsg("refine-note", api.errorLines(e), `Refinement ${run.sweepId}: ${action} refused`);
  }
  refreshSoon();
}

// ------------------------------------------------------------------ reading its state
let refreshing = false;
let again = false;
const refreshSoon = coalesced(() => refresh(), 200);

// GET /jobs/{id} (or the sweep, for a refinement this page did not start); new rounds bring their validation.
async function refresh() {
  if (!run) return;
  if (refreshing) {
    again = true;
    return;
  }
  refreshing = true;
  const r = run;
  try {
    if (r.jobId !== null) {
      const job = await api.get(`/jobs/${r.jobId}`);
      take(r, job.result, job.result ? job.result.state : job.state, job.error);
    } else {
      const sweep = await api.get(`/sweeps/${r.sweepId}`);
      take(r, sweep.refinement, sweep.state, sweep.error);
      r.pauseReason = sweep.pause_reason;
    }
    if (r.refinement && r.refinement.rounds.length !== r.roundsSeen) await loadValidations(r);
  } catch (e) {
    if (r === run) {
      r.queuedNote = false;
      showMsg("refine-note", api.errorLines(e), `Refinement ${r.sweepId}`);
    }
  } finally {
    refreshing = false;
  }
  if (r === run) render();
  if (again) {
    again = false;
    refresh();
  }
}

function take(r, refinement, state, error) {
  if (refinement) r.refinement = refinement;
  if (state) r.state = state;
  r.error = error || null;
}

// The source's latest validation (else round 0's, when round 0 measured the source's non-ok cells into
// a map of its own) and the latest round's map's, each once per new round.
async function loadValidations(r) {
  const ref = r.refinement;
  const rounds = ref.rounds;
  const latest = rounds[rounds.length - 1];
  const first = r.roundsSeen <= 0;     // before round 0's validation, and once it is there
  r.roundsSeen = rounds.length;
  if (first) {
    const own = await validationOf(ref.source_map_id);
    if (own) {
      r.source = { mapId: ref.source_map_id, validation: own, label: `source map ${ref.source_map_id}` };
    } else if (rounds[0]) {
      r.source = { mapId: rounds[0].map_id, validation: await validationOf(rounds[0].map_id, true),
        label: `map ${rounds[0].map_id} = map ${ref.source_map_id}, non-ok cells measured again` };
    }
  }
  if (latest) {
    r.refined = { mapId: latest.map_id, validation: await validationOf(latest.map_id, true),
      label: `refined map ${latest.map_id} (round ${latest.round})` };
  }
}

// the map's latest validation, or null (never validated: asked of the map first, no 404 logged)
async function validationOf(id, known) {
  if (!known) {
    const m = await api.get(`/maps/${id}`);
    if (!m.validation) return null;
  }
  return api.get(`/maps/${id}/validation`);
}

// ------------------------------------------------------------------ live events
function onRefinementProgress(p) {
  if (!run || p.sweep_id !== run.sweepId) {
    if (active()) return;
    follow(fresh(p.sweep_id, null));    // one started elsewhere (the API, another page): the bench is doing it
  }
  const live = run.live;
  if (p.round !== live.round || p.phase !== live.phase) {
    live.measured = 0;
    live.validated = new Set();
    live.total = null;
    live.toMeasure = null;
  }
  const m = /^measuring (\d+)/.exec(p.what || "");
  if (m) live.toMeasure = Number(m[1]);
  Object.assign(live, { round: p.round, phase: p.phase, what: p.what, mapId: p.map_id, cellsAdded: p.cells_added });
  if (["queued", "paused", "interrupted"].includes(run.state) && p.phase !== "done") run.state = "running";
  render();
  refreshSoon();
}

function onJobProgress(p) {
  if (p.kind !== "refinement" || !run || !active()) return;
  if (run.jobId === null) run.jobId = p.job_id;     // one worker: the refinement running is the one followed
  if (p.job_id !== run.jobId) return;
  const live = run.live;
  if (p.round !== live.round) {
    live.round = p.round;
    live.validated = new Set();
  }
  live.phase = "validate";
  const op = (p.cell && p.cell.operating_point) || {};
  live.validated.add(`${op.torque_nm}/${op.speed_rpm}/${op.udc_v}`);
  live.total = p.total;
  render();
}

function onSweepPoint(p) {
  if (!run || p.sweep_id !== run.sweepId) return;
  run.live.measured += 1;
  render();
}

function onSweepProgress(p) {
  if (!run || p.sweep_id !== run.sweepId) return;
  run.state = p.state;
  run.pauseReason = p.pause_reason || null;
  render();
  refreshSoon();
}

function onJobState(p) {
  if (p.kind !== "refinement" || !run) return;
  if (run.jobId === null && active()) run.jobId = p.job_id;
  if (p.job_id === run.jobId) refreshSoon();
}

// ------------------------------------------------------------------ drawing
function render() {
  const box = $("map-refine");
  box.dataset.active = run ? "1" : "";
  $("refine-btn").disabled = mapId === null || active();
  $("refine-cancel").hidden = !active();
  $("refine-resume").hidden = !run || !["paused", "interrupted"].includes(run.state);
  renderProgress();
  renderOutcome();
  renderRounds();
  drawPlots();
}

function renderProgress() {
  const p = $("refine-progress");
  if (!run) {
    p.dataset.phase = "";
    p.dataset.round = "";
    setText("refine-progress", "");
    return;
  }
  const ref = run.refinement;
  const live = run.live;
  const running = active();
  // the live event is newer than the last poll while running; the job's state once it ended
  const phase = running && live.phase ? live.phase : (ref ? ref.phase : live.phase);
  const round = running && live.phase ? live.round : roundOf(ref);
  const added = running && live.cellsAdded !== undefined ? live.cellsAdded : (ref ? ref.cells_added : 0);
  const mapNow = running && live.mapId ? live.mapId : (ref ? ref.map_id : null);
  const maxCells = ref ? ref.max_cells : Number($("refine-max-cells").value);
  let doing;
  if (phase === "measure") {
    doing = live.toMeasure !== null && running ? `measuring ${live.toMeasure} cell(s): ${live.measured} done` :
      "measuring cells";
  } else if (phase === "place") {
    doing = "placing breakpoints from the theta* identified between them";
  } else if (phase === "validate") {
    doing = `validating map ${mapNow ?? "—"}` +
      (running && live.total ? `: ${live.validated.size} of ${live.total} points` : "");
  } else {
    doing = running ? (phase || "starting") : "finished";
  }
  const state = ["running", "done"].includes(run.state) ? "" :
    ` · ${run.state}` + (run.pauseReason ? `: ${run.pauseReason}` : "");
  p.dataset.phase = phase || "";
  p.dataset.round = round === null || round === undefined ? "" : String(round);
  p.dataset.state = run.state;
  setText("refine-progress", `refinement ${run.sweepId}` + (ref ? ` of map ${ref.source_map_id}` : "") +
    ` · round ${round ?? "—"} · ${doing} · ${added} of max ${maxCells} cells identified${state}`);
}

// the round in progress: the rounds validated so far (round k is validated k-th); the last one when done
function roundOf(ref) {
  if (!ref) return null;
  const n = ref.rounds.length;
  return ref.phase === "done" && n ? ref.rounds[n - 1].round : n;
}

function renderOutcome() {
  const box = $("refine-outcome");
  const ref = run && run.refinement;
  if (!run || active() || !ref) {
    box.hidden = true;
    box.replaceChildren();
    return;
  }
  let level;
  let text;
  const last = ref.rounds[ref.rounds.length - 1];
  if (ref.state === "done" && ref.holds) {
    level = "ok";
    text = `Holds: all ${last.points} points of map ${ref.map_id} reach ${fmt(ref.target_db)} dB in the drive's LUT mode ` +
      `(${ref.cells_added} of max ${ref.max_cells} cells identified, ${ref.rounds.length} round(s)).`;
  } else if (ref.state === "done") {
    level = "warn";
    text = `Stopped: ${ref.stopped || "ended before every point held"} — map ${ref.map_id}, ` +
      `${ref.cells_added} of max ${ref.max_cells} cells identified, ${ref.rounds.length} round(s).`;
  } else {
    level = ref.state === "cancelled" ? "warn" : "error";
    text = `Refinement ${ref.state}${run.error ? ": " + run.error : ""} — latest map ${ref.map_id}, ` +
      `${ref.cells_added} cell(s) identified.`;
  }
  const placed = ref.placement || [];
  if (placed.length) {        // placement from curves came before the first validation
    const count = (axis) => placed.reduce((n, p) => n + ((p.inserted || {})[axis] || []).length, 0);
    text += ` Placed from curves first: ${placed.length} round(s), ${count("torque_nm")} torque and ` +
      `${count("speed_rpm")} speed value(s) inserted, ${placed[placed.length - 1].bytes} bytes.`;
  }
  if (run.queuedNote) {      // the outcome replaces the "queued" line (an error shown there stays)
    run.queuedNote = false;
    showMsg("refine-note", null);
  }
  box.className = `msg ${level}`;
  box.dataset.holds = ref.holds ? "1" : "0";
  box.dataset.state = ref.state;
  box.replaceChildren(el("span", null, text + " "));
  const open = el("button", { type: "button", class: "small", "data-testid": "refine-open-map",
    "data-map-id": String(ref.map_id) }, `open map ${ref.map_id} in the map view`);
  open.addEventListener("click", () => openMap(ref.map_id));
  box.appendChild(open);
  box.hidden = false;
}

function renderRounds() {
  const ref = run && run.refinement;
  const rounds = ref ? ref.rounds : [];
  $("refine-rounds").hidden = rounds.length === 0;
  $("refine-round-rows").replaceChildren(...rounds.map((r) => {
    const inserted = Object.entries(r.inserted || {}).filter(([, v]) => v.length)
      .map(([axis, v]) => `${axis} ${v.map((x) => fmt(x)).join(", ")}`).join("; ");
    const open = el("button", { type: "button", class: "small", title: "show this map in the map view" }, `map ${r.map_id}`);
    open.addEventListener("click", () => openMap(r.map_id));
    const mapCell = el("td");
    mapCell.appendChild(open);
    const tr = el("tr", { "data-testid": "refine-round", dataset: { round: String(r.round), mapId: String(r.map_id) } });
    tr.append(el("td", null, String(r.round)), mapCell, el("td", null, String(r.points)),
      el("td", null, String(r.below_target)), el("td", null, fmt(r.grid_median_db, 1)),
      el("td", null, fmt(r.midpoint_median_db, 1)), el("td", null, fmt(r.min_db, 1)),
      el("td", null, inserted || "—"), el("td", null, `${r.new_cells} new, ${r.remeasured} again`));
    return tr;
  }));
}

function drawPlots() {
  const show = Boolean(run && (run.source || run.refined));
  $("refine-plots").hidden = !show;
  $("refine-legend").hidden = !show;
  if (!show || !figures.plotlyLoaded()) return;
  const target = run.refinement ? run.refinement.target_db : Number($("refine-target").value);
  heat("plot-refine-source", run.source, target);
  heat("plot-refine-refined", run.refined, target);
}

function heat(div, view, target) {
  if (!view || !view.validation) {
    figures.purge(div);
    $(div).dataset.mapId = "";
    return;
  }
  const cells = view.validation.cells;
  const udcs = [...new Set(cells.map((c) => Number(c.operating_point.udc_v)))];
  const at = udcs.includes(udc) ? udc : udcs[0];
  const below = cells.filter((c) => c.status !== "measured" || c.suppression_db === null ||
    c.suppression_db < target).length;
  const title = `${view.label} · ${cells.length} points, ${below} below ${fmt(target)} dB @ ${fmt(at)} V`;
  $(div).dataset.mapId = String(view.mapId);
  figures.draw(div, figures.validationHeatmap(cells, at, { title }));
}
