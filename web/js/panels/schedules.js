// Panel (2a): schedules — a sweep at the times of a cron expression in an IANA time zone. Lists each
// schedule with its next runs and its recent runs (the sweep each submitted and the outcome), turns
// them on and off, deletes them, and creates one from the form.
import * as api from "../api.js";
import { coalesced } from "../coalesce.js";
import { $, el, showMsg } from "../dom.js";
import { runLevel, shortTime } from "../format.js";
import { submittedGrid } from "../grid-form.js";
import * as benchChoice from "../bench-choice.js";

const RELOAD_DEBOUNCE_MS = 300;
const NEXT_SHOWN = 3;            // next runs per row
const RUNS_SHOWN = 5;            // recent runs per row
let schedules = [];
let openSweep = () => {};

// openSweepOf(sweepId): what a run's "sweep N" link does.
export function init({ openSweepOf }) {
  openSweep = openSweepOf || openSweep;
  try {
    $("schedule-timezone").value = Intl.DateTimeFormat().resolvedOptions().timeZone || "UTC";
  } catch (_) { /* keep UTC */ }
  $("schedule-form").addEventListener("submit", submit);
}

export async function reload() {
  try {
    schedules = await api.get("/schedules");
    render();
  } catch (_) {
    /* shown by the live indicator; keep the last list */
  }
}

// A sweep changed state: a schedule's run may show it.
export function onSweepProgress(p) {
  if (schedules.some((s) => s.runs.some((r) => r.sweep_id === p.sweep_id))) scheduleReload();
}

export const scheduleReload = coalesced(() => reload(), RELOAD_DEBOUNCE_MS);

function render() {
  $("schedule-empty").hidden = schedules.length > 0;
  $("schedule-rows").replaceChildren(...schedules.map(row));
}

function row(s) {
  const tr = el("tr", { "data-testid": "schedule-row", "data-schedule-id": String(s.id),
    "data-enabled": String(s.enabled) });
  tr.appendChild(el("td", { class: "num" }, String(s.id)));
  tr.appendChild(el("td", null, s.name));
  tr.appendChild(el("td", { title: `time zone ${s.timezone}` }, `${s.cron} (${s.timezone})`));

  const next = el("td", { class: "next-cell", "data-testid": "schedule-next" });
  if (s.next_runs.length === 0) next.textContent = "—";
  for (const t of s.next_runs.slice(0, NEXT_SHOWN)) next.appendChild(el("div", { title: t }, t.replace("T", " ")));
  tr.appendChild(next);

  const runs = el("td", { class: "runs-cell wide", "data-testid": "schedule-runs" });
  if (s.runs.length === 0) runs.textContent = "never fired";
  for (const r of s.runs.slice(0, RUNS_SHOWN)) {
    const line = el("div", { class: "run", "data-testid": "schedule-run", "data-outcome": r.outcome, title: r.note || "" });
    line.appendChild(el("span", { class: "time" }, shortTime(r.due_at) + " "));
    line.appendChild(el("span", { class: "badge", "data-level": runLevel(outcomeState(r.outcome)) }, r.outcome));
    if (r.sweep_id !== null && r.sweep_id !== undefined) {
      const a = el("a", { href: "#sweeps" }, ` sweep ${r.sweep_id}`);
      a.addEventListener("click", () => openSweep(r.sweep_id));
      line.appendChild(a);
      if (r.sweep_state) line.appendChild(el("span", { class: "row-note" }, ` (${r.sweep_state})`));
    }
    runs.appendChild(line);
  }
  tr.appendChild(runs);

  const enabled = el("td");
  const toggle = el("input", { type: "checkbox", "data-testid": "schedule-enabled",
    title: s.enabled ? "fires at its times; untick to stop it" : "does not fire; tick to start it (counts from now)" });
  toggle.checked = s.enabled;
  toggle.addEventListener("change", () => change(s.id, { enabled: toggle.checked }, toggle));
  enabled.appendChild(toggle);
  tr.appendChild(enabled);

  const act = el("td", { class: "actions" });
  const del = el("button", { type: "button", class: "small", "data-action": "cancel", "data-testid": "schedule-delete" },
    "delete");
  del.addEventListener("click", () => remove(s.id, s.name));
  act.appendChild(del);
  tr.appendChild(act);
  return tr;
}

// a run's outcome coloured like a run state
function outcomeState(outcome) {
  return { started: "running", queued: "queued", skipped: "paused", missed: "cancelled", failed: "failed" }[outcome];
}

async function change(id, body, input) {
  showMsg("schedule-error", null);
  try {
    await api.send("PATCH", `/schedules/${id}`, body);
  } catch (e) {
    if (input) input.checked = !input.checked;
    showMsg("schedule-error", api.errorLines(e), `schedule ${id} not changed (HTTP ${e.status || "?"})`);
  }
  scheduleReload();
}

async function remove(id, name) {
  showMsg("schedule-error", null);
  try {
    await api.send("DELETE", `/schedules/${id}`);
    showMsg("schedule-ok", [`Schedule ${id} (${name}) deleted; its sweeps stay.`]);
  } catch (e) {
    showMsg("schedule-error", api.errorLines(e), `schedule ${id} not deleted (HTTP ${e.status || "?"})`);
  }
  scheduleReload();
}

async function submit(ev) {
  ev.preventDefault();
  const f = ev.target;
  const grid = submittedGrid(f, "schedule-error", "schedule-ok");
  if (!grid) return;
  const body = { name: f.elements.name.value.trim(), cron: f.elements.cron.value.trim(),
    timezone: f.elements.timezone.value.trim(), sweep: { grid, method: f.elements.method.value } };
  const btn = $("schedule-submit");
  btn.disabled = true;
  try {
    const s = await api.post("/schedules", benchChoice.withBench(body));
    showMsg("schedule-ok", [`Schedule ${s.id} (${s.name}) added; next run ${s.next_runs[0] || "—"}.`]);
    schedules = [...schedules.filter((x) => x.id !== s.id), s].sort((a, b) => a.id - b.id);
    render();
  } catch (e) {
    showMsg("schedule-error", api.errorLines(e),
      e.status ? `Schedule rejected (HTTP ${e.status}):` : "Schedule request failed:");
  } finally {
    btn.disabled = false;
  }
}
