// Small DOM helpers shared by the panels. API data goes in with textContent, never innerHTML.
import { deviceLevel } from "./format.js";

export const $ = (id) => document.getElementById(id);

// <tag attrs>text</tag>; attrs.dataset is merged into the element's dataset.
export function el(tag, attrs, text) {
  const e = document.createElement(tag);
  if (attrs) for (const [k, v] of Object.entries(attrs)) {
    if (k === "dataset") Object.assign(e.dataset, v);
    else e.setAttribute(k, v);
  }
  if (text !== undefined) e.textContent = text;
  return e;
}

export function setText(id, text, title) {
  const e = $(id);
  if (!e) return;
  if (e.textContent !== text) e.textContent = text;  // no needless relayout at 1 Hz
  if (title !== undefined) e.title = title;
}

// A yes/no flag, coloured ok when it equals goodWhen.
export function setFlag(id, value, goodWhen, yes, no) {
  const e = $(id);
  if (value === null || value === undefined) {
    e.textContent = "—";
    e.dataset.level = "";
    return;
  }
  e.textContent = value ? (yes || "yes") : (no || "no");
  e.dataset.level = (Boolean(value) === goodWhen) ? "ok" : "bad";
}

// A CiA 402 state badge.
export function setDeviceState(id, state) {
  const e = $(id);
  e.textContent = state ? String(state) : "—";
  e.dataset.level = deviceLevel(state);
}

// Message box: one line alone, several as a list, under an optional bold title; none hides it.
export function showMsg(id, lines, title) {
  const box = $(id);
  box.replaceChildren();
  if (!lines || lines.length === 0) {
    box.hidden = true;
    return;
  }
  if (title) box.appendChild(el("strong", null, title));
  if (lines.length === 1 && !title) {
    box.textContent = lines[0];
  } else {
    const ul = el("ul");
    for (const line of lines) ul.appendChild(el("li", null, line));
    box.appendChild(ul);
  }
  box.hidden = false;
}
