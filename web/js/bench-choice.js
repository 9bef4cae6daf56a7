// The bench a new run goes to, in a lab of several benches on one database: the top bar's picker.
// Its default is this service's own bench; a run for another bench is stored and waits for that
// bench's service. Every form that starts a run (identify, sweep, schedule, validate, refine) sends
// its body through withBench().
import { $, el } from "./dom.js";

let own = null;  // this service's bench name (GET /benches, `own`)

// The chosen bench, or null for this service's own.
export function chosen() {
  const pick = $("bench-pick");
  const value = pick ? pick.value : "";
  return value && value !== own ? value : null;
}

// A run's request body with `bench` when another bench is chosen (the service's default otherwise).
export function withBench(body) {
  const bench = chosen();
  return bench ? { ...body, bench } : body;
}

// The picker's choices from GET /benches; the choice made is kept while that bench is listed.
export function setBenches(benches) {
  const pick = $("bench-pick");
  if (!pick) return;
  const mine = benches.find((b) => b.own);
  own = mine ? mine.name : own;
  const keep = pick.value || own;
  const names = benches.map((b) => b.name);
  const current = [...pick.options].map((o) => o.value);
  if (current.join("\n") !== names.join("\n")) {
    pick.replaceChildren(...benches.map((b) => el("option", { value: b.name },
      b.name + (b.own ? " (this service)" : b.online ? "" : " (offline)"))));
  }
  pick.value = names.includes(keep) ? keep : (own || "");
}
