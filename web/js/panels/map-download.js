// The map shown in the Map panel into the drive's LUT (POST /maps/{id}/download, operator token).
// "with fill" (default on) takes the filled cells (not ok, carrying a fill: service/maps/fill.py) into
// the LUT; off, the drive injects only at ok cells. Success shows the CRC the drive read back and what
// went in; a refusal shows the service's message. A map with cells that would inject nothing under
// the chosen fill is refused without force; then this offers a second, explicit "download anyway"
// that sends force=true.
import * as api from "../api.js";
import { $, el, showMsg } from "../dom.js";

let shown = null;   // {id, cells, ok, filled} of the map in the Map panel

export function init() {
  $("map-download").addEventListener("click", () => download(false));
  // the fill choice sits beside the button (built here: the page's markup stays the Map panel's)
  if (!$("map-download-fill")) {
    const box = el("input", { type: "checkbox", id: "map-download-fill", "data-testid": "map-download-fill" });
    box.checked = true;
    const label = el("label", { for: "map-download-fill", title: "take the filled cells (not ok, carrying a fill) " +
      "into the LUT; off: the drive injects only at ok cells" });
    label.append(box, el("span", null, "with fill"));
    $("map-download").insertAdjacentElement("afterend", label);
  }
}

// main.js calls this for every map the Map panel draws (m: GET /maps/{id}); a redraw of the same
// map (another U_dc slice) keeps the last download's message.
export function showFor(m) {
  if (shown && shown.id === m.id) return;
  const ok = m.cells.filter((c) => c.status === "ok").length;
  const filled = m.cells.filter((c) => c.status !== "ok" && c.filled).length;
  shown = { id: m.id, cells: m.cells.length, ok, filled };
  $("map-download").dataset.mapId = String(m.id);
  $("map-download").disabled = false;
  $("map-download-fill").title = `take the ${filled} filled cell(s) into the LUT; off: the drive injects only ` +
    `at the ${ok} ok cell(s)`;
  showMsg("map-download-msg", null);
}

async function download(force) {
  if (!shown) return;
  const map = shown;
  const fill = $("map-download-fill").checked;
  const box = $("map-download-msg");
  $("map-download").disabled = true;
  box.className = "msg info";
  box.dataset.outcome = "pending";
  showMsg("map-download-msg", [`Downloading map ${map.id} into the drive${fill ? "" : " (without fill)"}…`]);
  const query = [force ? "force=true" : "", fill ? "" : "fill=false"].filter(Boolean).join("&");
  try {
    const r = await api.post(`/maps/${map.id}/download${query ? "?" + query : ""}`);
    box.className = "msg ok";
    box.dataset.outcome = "ok";
    // filled_cells / interpolation: in the receipt once the service reports them
    const filled = r.filled_cells !== undefined && r.filled_cells !== null ? r.filled_cells : null;
    const filledText = filled === null ? "" : (fill ? ` · ${filled} filled` : " · fill left out");
    showMsg("map-download-msg", [`Map ${r.map_id} is in the drive: CRC-32 ${r.crc32} read back · ` +
      `${r.valid_cells} of ${r.cells} cells ok${filledText} · ${r.bytes} bytes` +
      (r.interpolation ? ` · ${r.interpolation} interpolation` : "") +
      (r.forced ? " (forced: partial map)" : "")]);
    box.dataset.filledCells = filled === null ? "" : String(filled);
  } catch (e) {
    box.className = "msg error";
    box.dataset.outcome = "refused";
    showMsg("map-download-msg", api.errorLines(e), `Map ${map.id} not downloaded`);
    // the partial-map refusal (409) gets the explicit way through
    const holes = map.cells - map.ok - (fill ? map.filled : 0);
    if (!force && e.status === 409 && map.ok > 0 && holes > 0) {
      const again = el("button", { type: "button", class: "small", "data-testid": "map-download-force" },
        `Download anyway (${holes} of ${map.cells} cells without injection)`);
      again.addEventListener("click", () => download(true));
      box.appendChild(again);
    }
  } finally {
    $("map-download").disabled = false;
  }
}
