// Panel (1): the bench as /bench/status reports it, and the live indicator in the top bar.
import { detailText } from "../api.js";
import { $, setDeviceState, setFlag, setText } from "../dom.js";
import { fmt, fmtInt, shortTime } from "../format.js";

// s: the /bench/status object (docs/interfaces.md, "REST shapes the dashboard reads").
export function render(s) {
  const drive = s.drive || {};
  const load = s.load || {};
  const daq = s.daq || {};
  setText("bench-name", s.bench || "—");
  setDeviceState("drive-state", drive.state);
  setText("drive-speed", fmt(drive.speed_rpm, 1));
  setText("drive-torque", fmt(drive.torque_nm, 3));
  setText("drive-udc", fmt(drive.udc_v, 2));
  setFlag("drive-heartbeat", drive.heartbeat_ok, true, "ok", "lost");
  setDeviceState("load-state", load.state);
  setText("load-speed", fmt(load.speed_rpm, 1));
  setText("daq-frames", fmtInt(daq.frames));
  setText("daq-crc", fmtInt(daq.crc_failures));
  setText("daq-gaps", fmtInt(daq.sequence_gaps));
  $("daq-crc").dataset.level = daq.crc_failures ? "warn" : "";
  $("daq-gaps").dataset.level = daq.sequence_gaps ? "warn" : "";
  setFlag("bench-connected", s.connected, true);
  setFlag("bench-busy", s.busy, false, "busy", "idle");
  $("bench-busy").dataset.level = s.busy ? "warn" : "ok";
  setText("bench-updated", s.updated_at ? "updated " + shortTime(s.updated_at) : "");
  const err = $("bench-error");
  if (s.error) {
    err.textContent = "bench error: " + detailText(s.error);
    err.hidden = false;
  } else {
    err.hidden = true;
  }
}

// c: the "connection" event of events.js, {mode, text}.
export function showConnection(c) {
  const live = $("live-mode");
  live.dataset.mode = c.mode;
  live.textContent = c.text;
}
