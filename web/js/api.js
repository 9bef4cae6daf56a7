// REST client of /api/v1: GET without a token (reading is open), POST with the bearer token,
// and every error response shaped into an ApiError whose .lines a panel can show as they are.

export const API_BASE = "/api/v1";

let tokenSource = () => "";

// main.js owns the token field; the client only asks for the current value when it sends.
export function useToken(source) {
  tokenSource = source;
}

export class ApiError extends Error {
  constructor(status, lines, detail) {
    super(lines.join("; "));
    this.name = "ApiError";
    this.status = status;    // HTTP status
    this.lines = lines;      // human-readable messages, one per problem
    this.detail = detail;    // the service's `detail`, as sent
  }
}

export async function get(path) {
  const r = await fetch(API_BASE + path, { headers: { Accept: "application/json" }, cache: "no-store" });
  if (!r.ok) throw await errorOf(r);
  return r.json();
}

export async function post(path, body) {
  const headers = { Accept: "application/json" };
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const token = tokenSource();
  if (token) headers.Authorization = "Bearer " + token;
  const r = await fetch(API_BASE + path, {
    method: "POST", headers, body: body === undefined ? undefined : JSON.stringify(body),
  });
  if (!r.ok) throw await errorOf(r);
  return r.status === 204 ? null : r.json();
}

// PATCH / DELETE with the bearer token (schedules); 204 answers give null.
export async function send(method, path, body) {
  const headers = { Accept: "application/json" };
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const token = tokenSource();
  if (token) headers.Authorization = "Bearer " + token;
  const r = await fetch(API_BASE + path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
  if (!r.ok) throw await errorOf(r);
  return r.status === 204 ? null : r.json();
}

// The messages of a failed request: ApiError.lines, or the message of a network error.
export function errorLines(e) {
  return e.lines || [String(e.message || e)];
}

// A service `detail` (string, validation list or object) as one line of text.
export function detailText(detail) {
  if (typeof detail === "string") return detail;
  if (Array.isArray(detail)) return detail.map((d) => (d && d.msg) || JSON.stringify(d)).join("; ");
  return JSON.stringify(detail);
}

async function errorOf(r) {
  let payload = null;
  try {
    payload = await r.json();
  } catch (_) { /* not JSON */ }
  const detail = payload && payload.detail !== undefined ? payload.detail : null;
  const lines = [];
  if (r.status === 401 || (r.status === 403 && detail === "Not authenticated")) {
    lines.push("token missing or invalid");
  } else if (r.status === 403) {
    lines.push("not allowed" + (detail ? ": " + detailText(detail) : " (operator role required)"));
  } else if (r.status === 422 && Array.isArray(detail)) {
    for (const d of detail) {
      const loc = Array.isArray(d.loc) ? d.loc.filter((p) => p !== "body").join(".") : String(d.loc || "");
      lines.push((loc ? loc + ": " : "") + (d.msg || JSON.stringify(d)));
    }
  } else if (detail !== null) {
    lines.push(detailText(detail));
  } else {
    lines.push(`HTTP ${r.status} ${r.statusText || ""}`.trim());
  }
  return new ApiError(r.status, lines, detail);
}
