// Panel (2c): one stored result (from the Identify panel or a map cell): its numbers, the method's
// details and the paper's figures (Fig. 9 transient, Fig. 10 spectrum and alpha, Fig. 8 grid).
import * as api from "../api.js";
import { $, el, setText, showMsg } from "../dom.js";
import { fmt, resultLevel, shortTime, sig } from "../format.js";
import * as figures from "../figures.js";

let shownSeq = 0;                // guards against a slow fetch overwriting a newer result

// GET /results/{id} and show it; source says where it was opened from ("map 3").
export async function openResult(id, source) {
  const seq = ++shownSeq;
  showMsg("result-message", null);
  try {
    const r = await api.get(`/results/${id}`);
    if (seq !== shownSeq) return;
    render(r, source);
    $("result").scrollIntoView({ behavior: "smooth", block: "start" });
  } catch (e) {
    if (seq !== shownSeq) return;
    showMsg("result-message", [`result ${id}: ${e.message}`]);
  }
}

// Show a result already at hand (a finished job's); a fetch still under way is dropped.
export function showResult(r, source) {
  shownSeq++;
  render(r, source);
}

function unitOf(key) {
  const k = String(key);
  if (/_deg$/.test(k)) return "°";
  if (/_db$/.test(k)) return "dB";
  if (/_per_s$/.test(k)) return "1/s";
  if (/_s$/.test(k)) return "s";
  if (/_fs$/.test(k)) return "FS";
  if (/_rpm$/.test(k)) return "rpm";
  if (/_rad$/.test(k)) return "rad";
  if (/_samples$|^stale_samples$/.test(k)) return "samples";
  return "";
}

function valueText(v) {
  if (v === null || v === undefined) return "—";
  if (typeof v === "boolean") return v ? "yes" : "no";
  if (typeof v === "number") return sig(v, 5);
  if (Array.isArray(v)) return JSON.stringify(v, (_, x) => (typeof x === "number" ? Number(sig(x, 4)) : x));
  return String(v);
}

// details {a: 1, fit: {gamma_deg: 3}} -> [["a", 1], ["fit.gamma_deg", 3]]
function flatten(obj, prefix, out) {
  for (const [k, v] of Object.entries(obj || {})) {
    const key = prefix ? `${prefix}.${k}` : k;
    if (v && typeof v === "object" && !Array.isArray(v)) flatten(v, key, out);
    else out.push([key, v]);
  }
  return out;
}

function render(r, source) {
  const d = r.details || {};
  const op = r.operating_point || {};
  $("result").dataset.empty = "";
  $("result").dataset.resultId = String(r.id);
  $("result-empty").hidden = true;
  setText("result-title", `#${r.id} · ${r.method} · T* ${fmt(op.torque_nm)} N·m · n ${fmt(op.speed_rpm)} rpm · ` +
    `U_dc ${fmt(op.udc_v)} V · h = ${fmt(r.harmonic_order)}` + (source ? ` · from ${source}` : ""));
  const st = $("result-status");
  st.hidden = false;
  st.textContent = r.status || "—";
  st.dataset.level = resultLevel(r.status);
  const message = r.message || r.error;
  if (r.status !== "ok") {
    showMsg("result-message", [message ? String(message) : "no message"], `status ${r.status}:`);
  } else {
    showMsg("result-message", null);
  }

  setText("result-gamma", fmt(r.gamma_deg, 2));
  setText("result-delta", fmt(r.delta_deg, 1));
  setText("result-suppression", fmt(r.suppression_db, 1));
  setText("result-plant-time", fmt(r.plant_time_s, 3));
  renderFacts(r, d, message);

  const tbody = $("result-details").tBodies[0];
  tbody.replaceChildren(...flatten(d, "", []).map(([k, v]) => {
    const tr = el("tr", null);
    tr.append(el("th", null, k), el("td", { class: "num" }, valueText(v)), el("td", { class: "unit" }, unitOf(k.split(".").pop())));
    return tr;
  }));
  setText("result-options", r.options ? "options: " + JSON.stringify(r.options) : "");

  renderFigures(r);
}

function renderFacts(r, d, message) {
  const facts = [];
  const fact = (label, value, unit, title) => {
    if (value === null || value === undefined || value === "") return;
    facts.push([label, value, unit || "", title]);
  };
  fact("θ_cos", sig(r.theta_cos, 5), "rad");
  fact("θ_sin", sig(r.theta_sin, 5), "rad");
  if (r.uncompensated) fact("|a| before", sig(r.uncompensated.amplitude), "FS", "h-th harmonic amplitude, no injection");
  if (r.residual) fact("|a| after", sig(r.residual.amplitude), "FS", "h-th harmonic amplitude with the identified θ");
  if (d.time_to_40db_s !== undefined) fact("time to −40 dB", sig(d.time_to_40db_s), "s", "plant time until the h-th amplitude fell 40 dB");
  if (d.model_phase_error_deg !== undefined) fact("model phase error", sig(d.model_phase_error_deg), "°", "phase of Ŝ (model) against the measured S");
  if (d.model_gain_error_db !== undefined) fact("model gain error", sig(d.model_gain_error_db), "dB", "gain of Ŝ (model) against the measured S");
  if (r.s_model) fact("Ŝ model", `${sig(r.s_model.gain)} ∠ ${sig(r.s_model.phase_deg)}°`, "", "secondary path model (eq. 14-20): gain ∠ phase");
  if (r.s_measured) fact("S measured", `${sig(r.s_measured.gain)} ∠ ${sig(r.s_measured.phase_deg)}°`, "", "secondary path measured online: gain ∠ phase");
  if (d.minimum) fact("grid minimum", `γ ${sig(d.minimum.gamma_deg)}°, δ ${sig(d.minimum.delta_deg)}°, |a| ${sig(d.minimum.amplitude_fs)} FS`, "");
  if (d.fit) fact("affine fit", `γ ${sig(d.fit.gamma_deg)}°, δ ${sig(d.fit.delta_deg)}°, rms ${sig(d.fit.rms_fs)} FS`, "");
  if (d.reported) fact("reported", String(d.reported), "", "which grid theta the result reports and verifies");
  if (d.converged !== undefined) fact("converged", d.converged ? "yes" : "no", d.diverged ? "(diverged)" : "");
  fact("windows used", r.windows_used !== undefined && r.windows_used !== null
    ? `${r.windows_used}${r.windows_discarded ? ` (+${r.windows_discarded} discarded)` : ""}` : null, "");
  if (message && r.status === "ok") fact("message", String(message), "");
  fact("bench", r.bench_identity, "");
  fact("software", r.software_version, "");
  fact("finished", r.finished_at ? shortTime(r.finished_at) : null, "");
  const dl = $("result-facts");
  dl.replaceChildren();
  for (const [label, value, unit, title] of facts) {
    const dt = el("dt", title ? { title } : null, label);
    const dd = el("dd", null);
    dd.appendChild(el("span", { class: "num" }, String(value)));
    if (unit) dd.appendChild(el("span", { class: "unit" }, unit));
    dl.append(dt, dd);
  }
  renderRecording(dl, r.recording);
}

// The raw recording (DAQ samples and θ setpoints, MF4): a download link, or why there is none.
function renderRecording(dl, rec) {
  if (!rec) return;
  const dd = el("dd", { "data-testid": "result-recording" });
  if (rec.available) {
    dd.appendChild(el("a", { href: rec.url, download: "", "data-testid": "result-recording-link" }, "raw recording (MF4)"));
    dd.appendChild(el("span", { class: "unit" }, `${sig(rec.bytes / 1e3, 3)} kB · ${rec.samples} samples · ${rec.setpoints} θ setpoints`));
  } else {
    dd.appendChild(el("span", null, `none: ${rec.error || "not written"}`));
  }
  dl.append(el("dt", { title: "DAQ samples counted as plant time and the θ setpoints, as ASAM MDF 4" }, "raw recording"), dd);
}

// Each figure's box is shown with its figure and hidden (its plot freed) without one; the boxes
// of a group are laid out before any of them is drawn, so each plot is sized in its final box.
function showFigures(...pairs) {
  for (const [divId, figure] of pairs) $(divId).closest("figure").hidden = !figure;
  for (const [divId, figure] of pairs) {
    if (figure) figures.draw(divId, figure);
    else figures.purge(divId);
  }
}

function renderFigures(r) {
  if (!figures.plotlyLoaded()) {
    setText("result-note", "Plotly.js did not load — plots cannot be drawn.");
    return;
  }
  const notes = [];
  const theta = figures.thetaTransient(r);
  showFigures(["plot-theta", theta], ["plot-amplitude", figures.amplitudeTransient(r)]);
  if (!theta) notes.push(`no θ transient for method ${r.method}`);
  const spectrum = figures.spectrum(r);
  showFigures(["plot-spectrum", spectrum]);
  if (!spectrum) notes.push("no spectrum stored");
  const alpha = figures.alphaSnippets(r);
  showFigures(["plot-alpha", alpha]);
  if (!alpha) notes.push("no α snippets stored");
  showFigures(["plot-grid", figures.gridSurface(r)]);   // Fig. 8 belongs to the grid method only
  setText("result-note", notes.length ? notes.join(" · ") : "");
}
