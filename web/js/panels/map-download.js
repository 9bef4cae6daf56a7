// The map shown in the Map panel into the drive's LUT (POST /maps/{id}/download, operator token).
// Success shows the CRC the drive read back; a refusal shows the service's message. A partial map
// (some cells not ok: no injection there) is refused without force; then this offers a second,
// explicit "download anyway" that sends force=true.
import * as api from "../api.js";
import { $, el, showMsg } from "../dom.js";

let shown = null;   // {id, cells, ok} of the map in the Map panel

export function init() {
  $("map-download").addEventListener("click", () => download(false));
}

// main.js calls this for every map the Map panel draws (m: GET /maps/{id}); a redraw of the same
// map (another U_dc slice) keeps the last download's message.
export function showFor(m) {
  if (shown && shown.id === m.id) return;
  const ok = m.cells.filter((c) => c.status === "ok").length;
  shown = { id: m.id, cells: m.cells.length, ok };
  $("map-download").dataset.mapId = String(m.id);
  $("map-download").disabled = false;
  showMsg("map-download-msg", null);
}

async function download(force) {
  if (!shown) return;
  const map = shown;
  const box = $("map-download-msg");
  $("map-download").disabled = true;
  box.className = "msg info";
  box.dataset.outcome = "pending";
  showMsg("map-download-msg", [`Downloading map ${map.id} into the drive…`]);
  try {
    const r = await api.post(`/maps/${map.id}/download${force ? "?force=true" : ""}`);
    box.className = "msg ok";
    box.dataset.outcome = "ok";
    showMsg("map-download-msg", [`Map ${r.map_id} is in the drive: CRC-32 ${r.crc32} read back · ` +
      `${r.valid_cells} of ${r.cells} cells ok · ${r.bytes} bytes` + (r.forced ? " (forced: partial map)" : "")]);
  } catch (e) {
    box.className = "msg error";
    box.dataset.outcome = "refused";
    showMsg("map-download-msg", api.errorLines(e), `Map ${map.id} not downloaded`);
    // the partial-map refusal (409) gets the explicit way through
    if (!force && e.status === 409 && map.ok > 0 && map.ok < map.cells) {
      const again = el("button", { type: "button", class: "small", "data-testid": "map-download-force" },
        `Download anyway (${map.cells - map.ok} of ${map.cells} cells without injection)`);
      again.addEventListener("click", () => download(true));
      box.appendChild(again);
    }
  } finally {
    $("map-download").disabled = false;
  }
}
