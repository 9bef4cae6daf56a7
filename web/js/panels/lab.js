// (0) The lab: every bench on this database (GET /benches), one service per bench: online or when it
// was last seen, its state, what it runs, how many jobs wait for it. Refreshed by main.js (timer, and
// job/sweep events of any bench); it also gives the top bar's bench picker its choices.
import * as api from "../api.js";
import { $, el, showMsg } from "../dom.js";
import * as benchChoice from "../bench-choice.js";

export async function reload() {
  let benches;
  try {
    benches = await api.get("/benches");
  } catch (e) {
    showMsg("lab-error", api.errorLines(e));
    return;
  }
  showMsg("lab-error", []);
  benchChoice.setBenches(benches);
  render(benches);
}

function render(benches) {
  const rows = benches.map((b) => {
    const tr = el("tr", { "data-testid": "lab-row", dataset: { bench: b.name, online: String(b.online) } });
    tr.appendChild(el("td", { "data-testid": "lab-name" }, b.name + (b.own ? " (this service)" : "")));
    const online = el("td", { "data-testid": "lab-online" }, b.online ? "online" : b.seen);
    online.dataset.level = b.online ? "ok" : "bad";
    tr.appendChild(online);
    tr.appendChild(el("td", { "data-testid": "lab-state" }, b.state));
    tr.appendChild(el("td", { "data-testid": "lab-running" }, b.running || "—"));
    tr.appendChild(el("td", { "data-testid": "lab-queue", class: "num" }, String(b.queue)));
    tr.appendChild(el("td", { "data-testid": "lab-last-seen" }, b.last_seen || "never"));
    tr.appendChild(el("td", null, b.host ? `${b.host}:${b.port}` : "—"));
    return tr;
  });
  $("lab-rows").replaceChildren(...rows);
  $("lab-empty").hidden = benches.length > 0;
}
