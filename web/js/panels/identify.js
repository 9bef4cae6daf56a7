// Panel (2b): identify one operating point, follow its job (SSE job.state plus a poll as a safety
// net) and hand the finished result to the result view.
import * as api from "../api.js";
import { $, setText, showMsg } from "../dom.js";
import { fmt, runLevel, shortTime } from "../format.js";
import * as benchChoice from "../bench-choice.js";

const JOB_ACTIVE = new Set(["queued", "running"]);
const JOB_POLL_MS = 1000;        // job poll period while SSE is down
const JOB_POLL_LIVE_MS = 2500;   // safety-net poll while SSE is live (job.state triggers a fetch)
const SEEN_STATES_KEPT = 200;
const OPTION_EXAMPLES = {
  adaptive: '{"mu_per_s": 25, "max_blocks": 40}',
  probe: '{"probe_max_deg": 4.0, "max_newton_steps": 4}',
  grid: '{"gamma_step_deg": 0.5, "delta_step_deg": 20}',
};
const OP_FIELDS = [["torque_nm", "torque T*"], ["speed_rpm", "speed n"], ["udc_v", "DC link voltage"]];
const FIELD_IDS = { torque_nm: "identify-torque", speed_rpm: "identify-speed", udc_v: "identify-udc",
  method: "identify-method", options: "identify-options" };

let job = null;                  // the identification job the panel follows
let jobTimer = null;
let jobFetching = false;
const seenJobStates = new Map(); // job id -> last state seen over SSE (may arrive before the POST answers)
let isLive = () => false;
let showResult = () => {};

// isLiveNow(): whether SSE is live (sets the poll period); showResultOf(result, source): the result view.
export function init({ isLiveNow, showResultOf }) {
  isLive = isLiveNow;
  showResult = showResultOf;
  $("identify-form").addEventListener("submit", submit);
  $("identify-cancel").addEventListener("click", cancel);
  const method = $("identify-method");
  const setExample = () => { $("identify-options").placeholder = OPTION_EXAMPLES[method.value] || "{}"; };
  method.addEventListener("change", setExample);
  setExample();
}

// After a reload: keep following an identification that is still queued or running.
export async function resume() {
  try {
    const list = await api.get("/jobs?limit=10");
    const j = list.find((x) => x.kind === "identification" && JOB_ACTIVE.has(x.state));
    if (j && !job) follow(j);
  } catch (_) { /* nothing to resume */ }
}

// SSE job.state {job_id, state, kind}
export function onJobState(p) {
  if (p.kind === "sweep") return;
  seenJobStates.set(p.job_id, p.state);
  if (seenJobStates.size > SEEN_STATES_KEPT) seenJobStates.delete(seenJobStates.keys().next().value);
  if (job && p.job_id === job.id && p.state !== job.state) {
    job.state = p.state;      // show the new state at once; the fetch brings the rest
    render();
    schedulePoll(0);
  }
}

function markInvalid(names) {
  for (const [name, id] of Object.entries(FIELD_IDS)) {
    if (names.has(name)) $(id).setAttribute("aria-invalid", "true");
    else $(id).removeAttribute("aria-invalid");
  }
}

async function submit(ev) {
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
    follow(await api.post("/identifications",
      benchChoice.withBench({ operating_point: op, method: f.elements.method.value, options })));
  } catch (e) {
    if (e.status === 422 && Array.isArray(e.detail)) {
      const names = new Set();
      for (const d of e.detail) for (const p of (Array.isArray(d.loc) ? d.loc : [])) names.add(String(p));
      markInvalid(names);
    }
    showMsg("identify-error", api.errorLines(e),
      e.status ? `Identification rejected (HTTP ${e.status}):` : "Identification request failed:");
  } finally {
    btn.disabled = false;
  }
}

function follow(j) {
  const handled = Boolean(job && job.id === j.id && job.handled);
  job = Object.assign({}, j, { handled });
  render();
  if (JOB_ACTIVE.has(job.state)) {
    const seen = seenJobStates.get(job.id);
    schedulePoll(seen && seen !== job.state ? 0 : undefined);
  } else finished();
}

function schedulePoll(delay) {
  clearTimeout(jobTimer);
  jobTimer = setTimeout(refresh, delay !== undefined ? delay : (isLive() ? JOB_POLL_LIVE_MS : JOB_POLL_MS));
}

async function refresh() {
  if (!job || jobFetching) return;
  jobFetching = true;
  const id = job.id;
  try {
    const j = await api.get(`/jobs/${id}`);
    if (job && job.id === id) follow(j);
  } catch (e) {
    if (job && job.id === id) {
      setText("identify-note", `cannot read job ${id}: ${e.message} — retrying`);
      schedulePoll(JOB_POLL_MS * 2);
    }
  } finally {
    jobFetching = false;
  }
}

function render() {
  $("identify-job").hidden = !job;
  if (!job) return;
  setText("identify-job-id", String(job.id));
  const st = $("identify-state");
  st.textContent = job.state;
  st.dataset.state = job.state;
  st.dataset.level = runLevel(job.state);
  $("identify-cancel").hidden = !JOB_ACTIVE.has(job.state);
  const req = job.request || {};
  const op = req.operating_point || {};
  let note = `${req.method || "?"} at T* ${fmt(op.torque_nm)} N·m, n ${fmt(op.speed_rpm)} rpm, U ${fmt(op.udc_v)} V`;
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

// Once per job: its failure reason, and its result into the result view.
function finished() {
  clearTimeout(jobTimer);
  if (!job || job.handled) return;
  job.handled = true;
  if (job.state === "failed") {
    showMsg("identify-error", [job.error ? api.detailText(job.error) : "no reason given"], `Job ${job.id} failed:`);
  }
  if (job.result) showResult(job.result, `identification job ${job.id}`);
  else if (job.state === "done") setText("identify-note", `job ${job.id} finished without a stored result`);
}

async function cancel() {
  if (!job) return;
  showMsg("identify-error", null);
  const id = job.id;
  try {
    follow(await api.post(`/jobs/${id}/cancel`));
  } catch (e) {
    showMsg("identify-error", api.errorLines(e), `cancel job ${id} failed (HTTP ${e.status || "?"})`);
    schedulePoll(0);
  }
}
