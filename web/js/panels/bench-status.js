// Panel (1): the bench as /bench/status reports it, every reading with its age, and the live
// indicator in the top bar. Ages count on in the page between updates (tick), so a value nobody
// refreshes (a run holding the bench, a service gone) reads as stale, never as current.
import { detailText } from "../api.js";
import { $, setDeviceState, setFlag, setText } from "../dom.js";
import { fmt, fmtInt, shortTime } from "../format.js";

const DEFAULT_STALE_S = 3;
// element id -> [group of the status, field]; the group's `ages` say how old each field is
const AGED = {
  "drive-state": ["drive", "state"], "drive-speed": ["drive", "speed_rpm"], "drive-torque": ["drive", "torque_nm"],
  "drive-udc": ["drive", "udc_v"], "drive-lut": ["lut", "status"],
  "load-state": ["load", "state"], "load-speed": ["load", "speed_rpm"],
  "run-speed": ["run", "speed_rpm"], "run-accel": ["run", "harmonic_amplitude_fs"],
};

let last = null;            // the last status object
let receivedAt = 0;         // Date.now() when it came
let serviceDown = false;

// s: the /bench/status object (docs/interfaces.md, "REST shapes the dashboard reads").
export function render(s) {
  last = s;
  receivedAt = Date.now();
  const drive = s.drive || {};
  const load = s.load || {};
  const daq = s.daq || {};
  const run = s.run || {};
  setText("bench-name", s.bench || "—");
  setDeviceState("drive-state", drive.state);
  setText("drive-speed", fmt(drive.speed_rpm, 1));
  setText("drive-torque", fmt(drive.torque_nm, 3));
  setText("drive-udc", fmt(drive.udc_v, 2));
  setFlag("drive-heartbeat", drive.heartbeat_ok, true, "ok", "lost");
  setText("drive-lut", lutText(s.lut || {}));
  setDeviceState("load-state", load.state);
  setText("load-speed", fmt(load.speed_rpm, 1));
  setText("daq-frames", fmtInt(daq.frames));
  // line errors warn; what the service's own flushes discarded and overruns while nobody read the
  // DAQ are not the line's fault: shown plain, for what they count
  setText("daq-crc", fmtInt(daq.crc_failures));
  setText("daq-gaps", fmtInt(daq.sequence_gaps));
  $("daq-crc").dataset.level = daq.crc_failures ? "warn" : "";
  $("daq-gaps").dataset.level = daq.sequence_gaps ? "warn" : "";
  setText("daq-flush-resyncs", fmtInt(daq.flush_resyncs));
  setText("daq-overruns", fmtInt(daq.overruns));
  setText("daq-overrun-samples", daq.overruns ? `${fmtInt(daq.overrun_samples_lost)} frames dropped` : "");
  // acceleration in rad/s^2 beside its fraction of the DAQ's full scale
  const fs = Number(s.accel_full_scale_rad_s2);
  const a = run.harmonic_amplitude_fs;
  setText("run-speed", fmt(run.speed_rpm, 1));
  setText("run-accel", a === null || a === undefined ? "—" : fmt(Number.isFinite(fs) ? a * fs : null, 3));
  setText("run-accel-fs", a === null || a === undefined ? "—" : fmt(a, 5));
  setText("run-plant-time", fmt(run.plant_time_s, 2));
  setText("accel-fs", fmt(s.accel_full_scale_rad_s2));
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
  tick();
}

// The LUT the drive reports it holds (0x2001): map id and CRC-32, or why there is none in force.
function lutText(lut) {
  if (!lut.status) return "—";
  const held = lut.map_id ? `map ${lut.map_id} · ${lut.crc32}` : "none";
  return lut.status === "last_download_refused" ? `${held} (last download refused)` : held;
}

// Every second (main.js) and on each status: ages counted on since the status came, stale marks.
export function tick() {
  if (!last) return;
  const since = (Date.now() - receivedAt) / 1000;
  const limit = Number(last.stale_after_s) || DEFAULT_STALE_S;
  for (const [id, [group, field]] of Object.entries(AGED)) {
    const g = last[group] || {};
    const age0 = g.ages ? g.ages[field] : undefined;
    const hasValue = g[field] !== null && g[field] !== undefined;
    mark(id, hasValue && age0 !== undefined && age0 !== null ? age0 + since : null, limit, hasValue);
  }
  const daqAge = last.daq ? last.daq.data_age_s : null;
  mark("daq-data", daqAge === null || daqAge === undefined ? null : daqAge + since, limit, true);
}

function mark(id, age, limit, hasValue) {
  const label = $(id + "-age");
  const value = $(id);
  const stale = serviceDown || !hasValue || age === null || age > limit;
  if (label) {
    label.textContent = age === null ? "" : age < 60 ? `${age.toFixed(1)} s ago` : `${Math.round(age / 60)} min ago`;
    label.dataset.stale = hasValue && stale ? "1" : "";
    label.title = stale ? `stale: older than ${limit} s` : "";
  }
  if (value && id !== "daq-data") value.dataset.stale = hasValue && stale ? "1" : "";
}

// c: the "connection" event of events.js, {mode, text}.
export function showConnection(c) {
  const live = $("live-mode");
  live.dataset.mode = c.mode;
  live.textContent = c.text;
  serviceDown = c.mode === "down";
  // the last readings stay on screen, struck through: the service cannot tell us anything now
  $("bench").dataset.unreachable = serviceDown ? "1" : "";
  const reach = $("service-reach");
  reach.textContent = serviceDown ? "unreachable" : c.mode === "connecting" ? "—" : "reachable";
  reach.dataset.level = serviceDown ? "bad" : c.mode === "connecting" ? "" : "ok";
  if (serviceDown) {
    setText("bench-connected", "unknown");
    $("bench-connected").dataset.level = "warn";
    setText("drive-heartbeat", "unknown");
    $("drive-heartbeat").dataset.level = "warn";
  }
  tick();
}
