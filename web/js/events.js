// Live updates: Server-Sent Events from /api/v1/events, with /bench/status polling whenever no
// bench.status has come over SSE for a while. Panels subscribe with on(type, fn); this module
// knows no panel.
//
// Types: the service's SSE events ("bench.status", "job.state", "sweep.progress", "sweep.point",
// "job.progress", "refinement.progress"; bench.status also from the fallback poll), and two of its own:
//   "connection" {mode: "connecting"|"live"|"poll"|"down", text}, when the mode changes;
//   "resync" {}, when SSE is back after a drop (events may have been missed: reload lists).
import * as api from "./api.js";

const SSE_TYPES = ["bench.status", "job.state", "sweep.progress", "sweep.point", "job.progress",
                   "refinement.progress"];
const POLL_MS = 2000;            // fallback poll period of /bench/status
const SSE_STALE_MS = 3500;       // no bench.status over SSE for this long -> poll
const SSE_RETRY_MS = 10000;      // the browser gave up on the stream: open it again after this

const handlers = new Map();      // type -> Set of functions
let lastLiveAt = 0;              // Date.now() of the last bench.status over SSE
let mode = "connecting";
let dropped = false;             // SSE failed since it was last open

export function on(type, fn) {
  if (!handlers.has(type)) handlers.set(type, new Set());
  handlers.get(type).add(fn);
  return () => handlers.get(type).delete(fn);
}

// True while bench.status arrives over SSE; false while the page polls.
export function isLive() {
  return Date.now() - lastLiveAt <= SSE_STALE_MS;
}

// Called once, from main.init(): first poll, the stream, and the fallback timer.
export function start() {
  pollStatus();
  openStream();
  setInterval(() => {
    if (!isLive()) pollStatus();
  }, POLL_MS);
}

function emit(type, payload) {
  for (const fn of handlers.get(type) || []) {
    // one failing subscriber must not keep the event from the others; the error still surfaces
    try {
      fn(payload);
    } catch (e) {
      reportError(e);
    }
  }
}

function setMode(next, text) {
  if (next === mode) return;
  mode = next;
  emit("connection", { mode, text });
}

async function pollStatus() {
  try {
    const status = await api.get("/bench/status");
    emit("bench.status", status);
    if (!isLive()) setMode("poll", "polling every 2 s");
  } catch (_) {
    setMode("down", "service unreachable");
  }
}

function openStream() {
  if (!window.EventSource) return;
  const stream = new EventSource(api.API_BASE + "/events");
  stream.addEventListener("open", () => {
    if (dropped) {
      dropped = false;
      emit("resync", {});
    }
  });
  stream.addEventListener("error", () => {
    dropped = true;
    if (stream.readyState === EventSource.CLOSED) {
      // the browser gave up (e.g. HTTP error); poll meanwhile and retry ourselves
      setTimeout(openStream, SSE_RETRY_MS);
    }
  });
  for (const type of SSE_TYPES) {
    stream.addEventListener(type, (ev) => {
      const payload = parse(ev.data);
      if (payload === null) return;
      if (type === "bench.status") {
        lastLiveAt = Date.now();
        setMode("live", "live");
      }
      emit(type, payload);
    });
  }
}

function parse(data) {
  try {
    return JSON.parse(data);
  } catch (_) {
    return null;
  }
}
