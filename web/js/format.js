// How values read on the page: numbers, times, and the colour level of a state (data-level).
// Pure functions, no DOM.

// v with `digits` decimals, "—" when absent.
export function fmt(v, digits) {
  if (v === null || v === undefined || v === "") return "—";
  const x = Number(v);
  if (!Number.isFinite(x)) return String(v);
  return digits === undefined ? String(x) : x.toFixed(digits);
}

// A counter with thousands separators.
export function fmtInt(v) {
  if (v === null || v === undefined) return "—";
  const x = Number(v);
  return Number.isFinite(x) ? x.toLocaleString("en-US") : String(v);
}

// n significant digits; exponent form for very large or small magnitudes.
export function sig(v, n) {
  if (v === null || v === undefined) return "—";
  const x = Number(v);
  if (!Number.isFinite(x)) return String(v);
  if (x === 0) return "0";
  const a = Math.abs(x);
  if (a >= 1e5 || a < 1e-3) return x.toExponential((n || 4) - 1);
  return String(Number(x.toPrecision(n || 4)));
}

// ISO 8601 -> "YYYY-MM-DD hh:mm:ss" in local time.
export function shortTime(iso) {
  if (!iso) return "—";
  const d = new Date(iso);
  if (isNaN(d)) return String(iso);
  const pad = (n) => String(n).padStart(2, "0");
  return `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ` +
    `${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}`;
}

// For the few strings that go into Plotly's HTML-ish titles and hover texts.
export function escapeHtml(s) {
  return s.replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" }[c]));
}

// CiA 402 state of the drive or load machine.
export function deviceLevel(state) {
  if (!state) return "";
  const s = String(state).toLowerCase();
  if (s === "operation_enabled") return "ok";
  if (s.includes("fault")) return "bad";
  if (s === "quick_stop_active") return "warn";
  return "idle";
}

// State of a sweep or a job.
export function runLevel(state) {
  switch (state) {
    case "done": return "ok";
    case "running": return "run";
    case "failed": return "bad";
    case "cancelled": case "paused": return "warn";
    default: return "idle";
  }
}

// Status of a result: only ok cells go into a LUT.
export function resultLevel(status) {
  if (status === "ok") return "ok";
  if (status === "no_authority" || status === "below_target") return "warn";
  return "bad";
}
