// The operating-point grid of a form (torque, speed, DC-link voltage as comma-separated numbers), read
// the same way by every form that asks for one (a sweep, a schedule's sweep).
import { showMsg } from "./dom.js";

const GRID_FIELDS = [["torque_nm", "torque"], ["speed_rpm", "speed"], ["udc_v", "DC link voltage"]];

// {vals} or {error}: the numbers of a comma-separated field (also the run-up form's orders)
export function parseList(str, name) {
  const parts = str.split(/[,;\s]+/).map((x) => x.trim()).filter((x) => x !== "");
  if (parts.length === 0) return { error: `${name}: enter at least one number` };
  const vals = [];
  for (const p of parts) {
    const v = Number(p);
    if (!Number.isFinite(v)) return { error: `${name}: "${p}" is not a number` };
    vals.push(v);
  }
  return { vals };
}

// {grid, errors}: the grid the form's torque_nm / speed_rpm / udc_v fields give, or what is wrong.
function readGrid(form) {
  const grid = {};
  const errors = [];
  for (const [key, label] of GRID_FIELDS) {
    const r = parseList(form.elements[key].value, label);
    if (r.error) errors.push(r.error);
    else grid[key] = r.vals;
  }
  return { grid, errors };
}

// {regime, errors}: the sweep request's `regime` from a form's speeds_around_onset checkbox and spacing_rpm
// field (null when the form has none or the box is not ticked: the grid is measured as entered).
function readRegime(form) {
  const box = form.elements.speeds_around_onset;
  if (!box || !box.checked) return { regime: null, errors: [] };
  const raw = form.elements.spacing_rpm ? form.elements.spacing_rpm.value.trim() : "";
  if (raw === "") return { regime: { speeds_around_onset: true }, errors: [] };   // the service's default spacing
  const spacing = Number(raw);
  if (!Number.isFinite(spacing)) return { regime: null, errors: [`spacing around the onset: "${raw}" is not a number`] };
  return { regime: { speeds_around_onset: true, spacing_rpm: spacing }, errors: [] };
}

// The start of every grid form's submit: clear the form's messages, read its grid, show what is wrong.
// Returns the grid, or null when the form said what to fix.
export function submittedGrid(form, errorId, okId) {
  const sweep = submittedSweep(form, errorId, okId);
  return sweep && sweep.grid;
}

// The same for a form that may also place speeds around the field-weakening onset (the sweep form):
// {grid, regime} (regime null when not asked for), or null when the form said what to fix.
export function submittedSweep(form, errorId, okId) {
  showMsg(errorId, null);
  showMsg(okId, null);
  const { grid, errors } = readGrid(form);
  const r = readRegime(form);
  errors.push(...r.errors);
  if (errors.length) {
    showMsg(errorId, errors, "Check the grid:");
    return null;
  }
  return { grid, regime: r.regime };
}
