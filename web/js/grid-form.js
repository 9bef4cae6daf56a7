// The operating-point grid of a form (torque, speed, DC-link voltage as comma-separated numbers), read
// the same way by every form that asks for one (a sweep, a schedule's sweep).
import { showMsg } from "./dom.js";

const GRID_FIELDS = [["torque_nm", "torque"], ["speed_rpm", "speed"], ["udc_v", "DC link voltage"]];

function parseList(str, name) {
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

// The start of every grid form's submit: clear the form's messages, read its grid, show what is wrong.
// Returns the grid, or null when the form said what to fix.
export function submittedGrid(form, errorId, okId) {
  showMsg(errorId, null);
  showMsg(okId, null);
  const { grid, errors } = readGrid(form);
  if (errors.length) {
    showMsg(errorId, errors, "Check the grid:");
    return null;
  }
  return grid;
}
