// ripplecal dashboard: bench status (SSE with polling fallback), sweeps, compensation maps,
// single identifications and the result view (paper Fig. 8, 9, 10). Native ES modules, no build
// step. This module wires the others: it subscribes the panels to the live events, hands each
// panel what it may ask of another, and starts every periodic timer (the fallback poll of
// /bench/status through events.start()). No other module does anything on import.
import * as api from "./api.js";
import * as catalog from "./catalog.js";
import * as events from "./events.js";
import * as benchStatus from "./panels/bench-status.js";
import * as sweeps from "./panels/sweeps.js";
import * as maps from "./panels/maps.js";
import * as mapDownload from "./panels/map-download.js";
import * as mapCompare from "./panels/map-compare.js";
import * as mapValidation from "./panels/map-validation.js";
import * as identify from "./panels/identify.js";
import * as runupsPanel from "./panels/runups.js";
import * as resultView from "./panels/result-view.js";
import * as schedules from "./panels/schedules.js";
import * as lab from "./panels/lab.js";
import { coalesced } from "./coalesce.js";

const TOKEN_KEY = "ripplecal.token";
const SWEEP_POLL_MS = 5000;      // sweep list refresh while SSE is down
const SCHEDULE_POLL_MS = 15000;  // schedules: next runs move on, firings happen between sweep events
const LAB_POLL_MS = 2000;        // the lab overview: other benches' heartbeats (last seen, online)

// The token field is remembered in localStorage; the API client reads it when it sends.
function bindToken() {
  const field = document.getElementById("token");
  try {
    field.value = localStorage.getItem(TOKEN_KEY) || "";
  } catch (_) { /* storage disabled */ }
  field.addEventListener("input", () => {
    try {
      localStorage.setItem(TOKEN_KEY, field.value.trim());
    } catch (_) { /* storage disabled */ }
  });
  api.useToken(() => field.value.trim());
}

async function init() {
  bindToken();
  try {
    await catalog.load();        // the forms' method choices and the export links, from the registries
  } catch (e) {
    reportError(e);
  }
  sweeps.init({ openMapOf: maps.select });
  mapCompare.init();
  // the drawn map goes to the validation panel (with its U_dc slice) and to the download button
  maps.init({ openResultOf: resultView.openResult, onMapShown: mapCompare.setMapA,
              shown: (m, udc) => { mapValidation.show(m, udc); mapDownload.showFor(m); } });
  mapValidation.init();
  mapDownload.init();
  events.on("job.state", mapValidation.onJobState);
  identify.init({ isLiveNow: events.isLive, showResultOf: resultView.showResult });
  runupsPanel.init();
  events.on("job.state", runupsPanel.onJobState);
  schedules.init({});
  events.on("sweep.progress", schedules.onSweepProgress);
  setInterval(schedules.reload, SCHEDULE_POLL_MS);

  events.on("connection", benchStatus.showConnection);
  events.on("bench.status", benchStatus.render);
  events.on("sweep.progress", sweeps.onProgress);
  events.on("sweep.progress", maps.onSweepProgress);
  events.on("sweep.point", sweeps.onPoint);
  events.on("job.state", sweeps.onJobState);
  events.on("job.state", identify.onJobState);
  // the lab overview: every bench's runs (events of any bench) and heartbeats (timer)
  const labSoon = coalesced(lab.reload, 300);
  events.on("job.state", labSoon);
  events.on("sweep.progress", labSoon);
  setInterval(lab.reload, LAB_POLL_MS);
  events.on("resync", () => {
    // SSE was down: sweep progress may have been missed
    sweeps.reload();
    maps.reload(false);
  });

  events.start();
  setInterval(() => {
    benchStatus.tick();      // ages count on between updates; stale marks appear by themselves
    sweeps.tick();           // elapsed time and ETA of running sweeps
  }, 1000);
  setInterval(() => {
    if (!events.isLive()) sweeps.reload();
  }, SWEEP_POLL_MS);
  sweeps.reload();
  maps.reload(true);
  schedules.reload();
  runupsPanel.reload();
  lab.reload();
  identify.resume();
}

// Module scripts run after the document is parsed, so the elements are there.
init();
