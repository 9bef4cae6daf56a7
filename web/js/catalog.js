// What the service offers, from its registries (GET /methods, /export-formats): the method choices
// of the sweep and identify forms and the map's export links are filled from here, never written
// into the page, so a method or a format added on the server shows up without touching the dashboard.
import * as api from "./api.js";
import { el } from "./dom.js";

export async function load() {
  const [methods, formats] = await Promise.all([api.get("/methods"), api.get("/export-formats")]);
  for (const id of ["sweep-method", "schedule-method", "identify-method"]) {
    const select = document.getElementById(id);
    select.replaceChildren(...methods.map((m) =>
      el("option", { value: m.name, title: m.summary }, id === "identify-method" ? `${m.name} — ${m.display_name}` : m.name)));
  }
  const exports = document.getElementById("map-exports");
  exports.replaceChildren("export: ", ...formats.flatMap((f, i) =>
    [i ? " " : "", el("a", { "data-format": f.name, href: "#", title: f.media_type }, f.display_name)]));
}
