// Plotly figure builders: data in, {data, layout, config} out. The only module that talks to
// Plotly (window.Plotly, from /vendor/plotly.min.js, loaded before the modules).
import { escapeHtml, fmt } from "./format.js";

const FONT = { family: "system-ui, -apple-system, Segoe UI, Roboto, sans-serif", size: 11 };
const CONFIG = { displaylogo: false, responsive: true };
const C_BEFORE = "#9aa4b2";
const C_AFTER = "#1b5fae";
const C_COS = "#1b5fae";
const C_SIN = "#d1495b";

export function plotlyLoaded() {
  return Boolean(window.Plotly);
}

// Draws `figure` into the div, then fits it to the size Plotly gave it (fit) and again whenever the figure is
// laid out anew (the window resized, a zoom).
export function draw(divId, figure) {
  window.Plotly.react(divId, figure.data, figure.layout, figure.config);
  const gd = document.getElementById(divId);
  fit(gd, figure);
  if (refits.has(divId)) gd.removeListener("plotly_relayout", refits.get(divId));
  const refit = () => fit(gd, figure);
  refits.set(divId, refit);
  gd.on("plotly_relayout", refit);
}

export function purge(divId) {
  refits.delete(divId);  // Plotly.purge drops the div's listeners
  if (window.Plotly) window.Plotly.purge(divId);
}

// ------------------------------------------------------------------ a drawn figure fitted to its size
// Measured once Plotly has laid a figure out, never guessed from the data: a title wider than the figure wraps at
// its " · " parts; a heat map (figure.heat) draws a cell's number only where it fits inside the cell, keeps the
// axis tick labels that clear the ones kept before them, and shrinks its grid-point marks to their cells (a
// refined map's non-uniform axes have cells a few pixels wide: the colour and the hover still say every value).
const refits = new Map();            // div id -> its plotly_relayout handler
const LINE_SPACING = 1.3;            // Plotly's, between the lines of a title
const LABEL_FONT_PX = [11, 9];       // a cell's number: the first size it fits at, else none
const LABEL_PAD_PX = 2;              // around a cell's number, inside its cell
const TICK_GAP_PX = 6;               // between two tick labels
const MARK_MAX_PX = 30;              // a grid-point mark in a cell at least that large
const MARK_MIN_PX = 6;               // smaller, a mark is a dot that hides its cell's colour: none
let measureCtx = null;

function textBox(text, px) {
  measureCtx = measureCtx || document.createElement("canvas").getContext("2d");
  measureCtx.font = `${px}px ${FONT.family}`;
  const m = measureCtx.measureText(String(text).replace(/<[^>]*>/g, ""));
  return { w: m.width, h: m.fontBoundingBoxAscent + m.fontBoundingBoxDescent };
}

// Draws the fitted figure; again while that moves the plot area (a wrapped title takes a line of its height).
function fit(gd, figure) {
  for (let pass = 0; pass < 3 && gd._fullLayout; pass++) {
    const area = plotArea(gd);
    const { width, height } = gd._fullLayout;
    const layout = Object.assign({}, figure.layout, wrappedTitle(figure.layout, width, height));
    const { data, axes } = figure.heat ? fittedHeatmap(gd, figure) : { data: figure.data, axes: {} };
    window.Plotly.react(gd, data, Object.assign(layout, axes), figure.config);
    if (plotArea(gd) === area) return;
  }
}

function plotArea(gd) {
  const fl = gd._fullLayout;
  return fl.xaxis ? `${fl.width}x${fl.height} ${fl.xaxis._length}x${fl.yaxis._length}` : `${fl.width}x${fl.height}`;
}

// The title in lines no wider than the figure (its " · " parts kept whole where they fit), centred in a top margin
// that holds them (Plotly centres the lines of a title on its anchor).
function wrappedTitle(layout, width, height) {
  const title = layout.title;
  if (!title || !title.text) return {};
  const px = (title.font && title.font.size) || FONT.size;
  const room = width * (1 - (title.x ?? 0.02)) - 8;
  const fits = (t) => textBox(t, px).w <= room;
  const lines = [];
  String(title.text).split(" · ").forEach((part, n) => {
    if (n > 0 && fits(`${lines[lines.length - 1]} · ${part}`)) {
      lines[lines.length - 1] += ` · ${part}`;
      return;
    }
    let line = n > 0 ? "·" : "";             // a continued line starts with the separator it was broken at
    for (const word of part.split(" ")) {    // a part wider than the figure: at its spaces
      if (line && line !== "·" && !fits(`${line} ${word}`)) {
        lines.push(line);
        line = word;
      } else line = line ? `${line} ${word}` : word;
    }
    lines.push(line);
  });
  const top = 8;
  const lineHeight = px * LINE_SPACING;
  const margin = Object.assign({}, layout.margin);
  margin.t = Math.max(margin.t || 0, Math.ceil(top + lines.length * lineHeight + 8));
  const centre = top + (lines.length * lineHeight) / 2;
  return {
    title: Object.assign({}, title,
      { text: lines.join("<br>"), yref: "container", y: 1 - centre / height, yanchor: "middle" }),
    margin,
  };
}

// figure.heat: {xs, ys, xEdges, yEdges, z, digits, marks (the index of its grid-point mark trace, or null),
// xTicks, yTicks (tick values, the ones to keep first first)}; the heat map is the figure's first trace.
function fittedHeatmap(gd, figure) {
  const h = figure.heat;
  const xa = gd._fullLayout.xaxis;
  const ya = gd._fullLayout.yaxis;
  // the room centred on each breakpoint inside its cell (a cell of a non-uniform axis reaches halfway to either
  // neighbour: its breakpoint is off its middle) and inside the plot area (a zoom cuts the edge cells): px, 0 if none
  const room = (values, edges, axis) => values.map((v, k) => {
    const at = axis.l2p(v);
    const [a, b] = edges[k].map((e) => Math.min(axis._length, Math.max(0, axis.l2p(e))));
    const half = Math.min(Math.abs(at - a), Math.abs(b - at));
    return at < 0 || at > axis._length ? 0 : 2 * half - 1;  // the heat map's 1 px gap
  });
  const widths = room(h.xs, h.xEdges, xa);
  const heights = room(h.ys, h.yEdges, ya);
  const colourOf = cellColour(gd._fullData[0]);
  const labels = { x: [], y: [], text: [], size: [], colour: [] };
  h.z.forEach((row, i) => row.forEach((v, j) => {
    if (v === null || v === undefined) return;
    const text = Number(v).toFixed(h.digits);
    const px = LABEL_FONT_PX.find((f) => {
      const box = textBox(text, f);
      return box.w + 2 * LABEL_PAD_PX <= widths[j] && box.h <= heights[i];
    });
    if (px === undefined) return;
    labels.x.push(h.xs[j]);
    labels.y.push(h.ys[i]);
    labels.text.push(text);
    labels.size.push(px);
    labels.colour.push(colourOf(v));
  }));
  const data = figure.data.map((trace, k) => {
    if (k !== h.marks) return trace;
    const cell = trace.x.map((x, n) => Math.min(widths[h.xs.indexOf(x)], heights[h.ys.indexOf(trace.y[n])]));
    return Object.assign({}, trace, { marker: Object.assign({}, trace.marker,
      { size: cell.map((c) => (c - 2 < MARK_MIN_PX ? 0 : Math.min(MARK_MAX_PX, c - 2))) }) });
  });
  data.push({ type: "scatter", mode: "text", x: labels.x, y: labels.y, text: labels.text,
    textfont: { family: FONT.family, size: labels.size, color: labels.colour }, hoverinfo: "skip", showlegend: false,
    name: "cell values" });
  const ticks = (values, axis, along) => {
    const kept = [];
    for (const v of values) {
      const at = axis.l2p(v);
      if (at < 0 || at > axis._length) continue;  // outside a zoom
      const half = textBox(fmt(v), FONT.size)[along] / 2;
      if (kept.every((k) => Math.abs(k.at - at) >= k.half + half + TICK_GAP_PX)) kept.push({ v, at, half });
    }
    const vals = kept.map((k) => k.v).sort((a, b) => a - b);
    return { tickvals: vals, ticktext: vals.map((v) => fmt(v)) };
  };
  const zoom = (axis) => ({ range: axis.range.slice() });   // a zoom the reader made stays
  return {
    data,
    axes: {
      xaxis: Object.assign({}, figure.layout.xaxis, zoom(xa), ticks(h.xTicks, xa, "w")),
      yaxis: Object.assign({}, figure.layout.yaxis, zoom(ya), ticks(h.yTicks, ya, "h")),
    },
  };
}

// The text colour for a cell's number: dark on a light cell, white on a dark one (the heat map trace as Plotly
// resolved it: its colour scale's stops and z range).
function cellColour(trace) {
  const stops = (trace.colorscale || []).map(([at, c]) => [at, rgbOf(c)]);
  const span = trace.zmax - trace.zmin || 1;
  return (v) => {
    const t = Math.min(1, Math.max(0, (v - trace.zmin) / span));
    const k = Math.max(1, stops.findIndex(([at]) => at >= t));
    const [a0, c0] = stops[k - 1];
    const [a1, c1] = stops[k];
    const f = a1 > a0 ? (t - a0) / (a1 - a0) : 0;
    const [r, g, b] = c0.map((x, n) => x + f * (c1[n] - x));
    return (r * 299 + g * 587 + b * 114) / 1000 > 128 ? "#1d2430" : "#ffffff";
  };
}

function rgbOf(colour) {
  const c = String(colour).trim();
  if (c.startsWith("#")) {
    const hex = c.length === 4 ? [...c.slice(1)].map((d) => d + d).join("") : c.slice(1, 7);
    return [0, 2, 4].map((i) => parseInt(hex.slice(i, i + 2), 16));
  }
  return (c.match(/[\d.]+/g) || [0, 0, 0]).slice(0, 3).map(Number);
}

// fn(point) on a click on a drawn figure; bound once per div.
export function onClick(divId, fn) {
  const div = document.getElementById(divId);
  if (div.dataset.clickBound || typeof div.on !== "function") return;
  div.dataset.clickBound = "1";
  div.on("plotly_click", (ev) => {
    const pt = ev && ev.points && ev.points[0];
    if (pt) fn(pt);
  });
}

// ------------------------------------------------------------------ compensation map
// gamma = |theta| (>= 0, clamped to gamma_max); delta = -atan2(theta_sin, theta_cos) is a phase,
// so it gets a cyclic colour scale over a full turn.
const CYCLIC = [[0, "#3b6fb6"], [0.25, "#3aa57a"], [0.5, "#e8c547"], [0.75, "#d1495b"], [1, "#3b6fb6"]];
// fill: a filled cell (not ok, carrying a fill: service/maps/fill.py) shows its fill's value, hatched
export const MAP_QUANTITIES = [
  { key: "gamma_deg", title: "γ — injection amplitude", unit: "deg", cbar: "γ (°)", sym: "γ",
    scale: "Viridis", range: "zero", digits: 2, fill: true },
  { key: "delta_deg", title: "δ — injection phase", unit: "deg", cbar: "δ (°)", sym: "δ",
    scale: CYCLIC, range: "phase", digits: 1, fill: true },
  { key: "suppression_db", title: "suppression of the h-th harmonic", unit: "dB", cbar: "dB",
    sym: "suppression", scale: "Cividis", range: "fixed", zmin: 0, zmax: 80, digits: 1 },
];

// Map b against map a (GET /maps/{a}/compare/{b}), drawn by mapHeatmap over compareCells().
export const COMPARE_QUANTITIES = [
  { key: "delta_theta_deg", title: "|Δθ| — map b against map a", unit: "deg", cbar: "|Δθ| (°)", sym: "|Δθ|",
    scale: [[0, "#fff5eb"], [0.5, "#fd8d3c"], [1, "#a63603"]], range: "zero", digits: 2 },
  { key: "predicted_suppression_db", title: "suppression b's θ would reach on a's bench", unit: "dB", cbar: "dB",
    sym: "predicted", scale: "Cividis", range: "fixed", zmin: 0, zmax: 80, digits: 1 },
];

// A comparison's cells as map cells: compared cells count as ok, the others carry why not.
export function compareCells(comparison) {
  return comparison.cells.map((c) => Object.assign({}, c, {
    status: c.compared ? "ok" : "not compared", result_id: null, quality: null,
  }));
}

// The cells of `map` at one DC-link voltage: torque on x, speed on y.
export function mapSlice(map, udc) {
  const cells = map.cells.filter((c) => Number(c.udc_v) === udc);
  const axis = (key) => ((map.axes && map.axes[key]) || [...new Set(cells.map((c) => c[key]))])
    .slice().sort((a, b) => a - b);
  return { udc, cells, xs: axis("torque_nm"), ys: axis("speed_rpm") };
}

// gamma, delta (deg) of a cell's theta: gamma = |theta|, delta = -atan2(theta_sin, theta_cos) in [0, 360)
function cellValue(c, key) {
  if (c[key] !== null && c[key] !== undefined) return c[key];
  if ((key !== "gamma_deg" && key !== "delta_deg") || c.theta_cos === null || c.theta_cos === undefined) return null;
  if (key === "gamma_deg") return Math.hypot(c.theta_cos, c.theta_sin) * 180 / Math.PI;
  return ((-Math.atan2(c.theta_sin, c.theta_cos) * 180 / Math.PI) % 360 + 360) % 360;
}

// The edges of the cells around the breakpoints of a (non-uniform) axis: halfway between
// neighbours, as far out at the ends as the first and last half-intervals (a one-value axis: +-0.5).
function cellEdges(values) {
  const v = values.map(Number);
  if (v.length === 1) return [[v[0] - 0.5, v[0] + 0.5]];
  return v.map((x, i) => {
    const lo = i === 0 ? x - (v[1] - v[0]) / 2 : (v[i - 1] + x) / 2;
    const hi = i === v.length - 1 ? x + (x - v[i - 1]) / 2 : (x + v[i + 1]) / 2;
    return [lo, hi];
  });
}

// One heatmap of a MAP_QUANTITIES entry; blank where a cell has no valid value. The axes are
// numeric: each breakpoint at its real position (a refined map's inserted speeds sit where they are).
// Filled cells (q.fill) show their fill's value under a hatch, with the fill's source in the hover.
export function mapHeatmap(slice, q) {
  const { udc, cells, xs, ys } = slice;
  const xi = new Map(xs.map((v, i) => [Number(v), i]));
  const yi = new Map(ys.map((v, i) => [Number(v), i]));
  const z = ys.map(() => xs.map(() => null));
  const text = ys.map((n) => xs.map((t) =>
    `T* ${t} N·m<br>n ${n} rpm<br>U<sub>dc</sub> ${udc} V<br><i>no cell</i>`));
  const filledAt = [];
  for (const c of cells) {
    const i = yi.get(Number(c.speed_rpm));
    const j = xi.get(Number(c.torque_nm));
    if (i === undefined || j === undefined) continue;
    const head = `T* ${fmt(c.torque_nm)} N·m<br>n ${fmt(c.speed_rpm)} rpm<br>U<sub>dc</sub> ${fmt(c.udc_v)} V<br>`;
    const click = (c.quality === "outlier" ? `<br><b>outlier</b>: ${escapeHtml(String(c.outlier_reason).split(" (")[0])}` : "") +
      (c.result_id ? "<br><i>click: result details</i>" : "");
    const filled = c.status !== "ok" && Boolean(c.filled);
    const fillText = filled ? `<br><b>filled</b> (status ${escapeHtml(String(c.status))}, not a result at its target)` +
      `<br>fill: ${escapeHtml(String(c.fill_source || "—"))}` : "";
    if (filled) filledAt.push([i, j]);
    const v = (c.status === "ok" || (filled && q.fill)) ? cellValue(c, q.key) : null;
    if (v !== null && v !== undefined) {
      z[i][j] = v;
      text[i][j] = head + `<b>${q.sym} = ${Number(v).toFixed(q.digits)} ${q.unit === "deg" ? "°" : q.unit}</b>` +
        fillText + click;
    } else {
      text[i][j] = head + `<b>status: ${escapeHtml(String(c.status))}</b> (no value)` + fillText + click;
    }
  }
  const trace = {
    type: "heatmap", x: xs, y: ys, z, text, hovertemplate: "%{text}<extra></extra>",
    hoverongaps: true, colorscale: q.scale,
    xgap: 1, ygap: 1,
    colorbar: { title: { text: q.cbar, side: "right" }, thickness: 12, len: 0.9 },
  };
  const finite = z.flat().filter((v) => v !== null);
  let rangeNote = "";
  if (q.range === "fixed") {
    // the same range for every map, so maps compare by colour; values outside it saturate
    [trace.zmin, trace.zmax] = [q.zmin, q.zmax];
    trace.colorbar.title.text = `${q.cbar} (fixed ${q.zmin}…${q.zmax})`;
    rangeNote = ` · colour ${q.zmin}…${q.zmax} ${q.unit}`;
  } else if (q.range === "zero" && finite.length) {
    trace.zmin = 0;
    trace.zmax = Math.max(...finite, 1e-6);
  } else if (q.range === "phase") {
    const lo = finite.length ? Math.min(...finite) : 0;
    const hi = finite.length ? Math.max(...finite) : 0;
    [trace.zmin, trace.zmax] = (lo >= 0 && hi > 180) ? [0, 360] : [-180, 180];
    trace.colorbar.tickvals = trace.zmin === 0 ? [0, 90, 180, 270, 360] : [-180, -90, 0, 90, 180];
  }
  const xEdges = cellEdges(xs);
  const yEdges = cellEdges(ys);
  const fillNote = filledAt.length ? ` · hatched: ${filledAt.length} filled` : "";
  // numeric axes, ticks at the breakpoints (those that fit: fit()); the cells span halfway to their neighbours
  const axis = (title, values, edges) => ({
    title: { text: title }, type: "linear", tickmode: "array", tickvals: values, ticktext: values.map((v) => fmt(v)),
    range: [edges[0][0], edges[edges.length - 1][1]], zeroline: false, showgrid: false, tickangle: 0, automargin: true,
  });
  const layout = {
    title: { text: `${slice.orderLabel || ""}${q.title} (${q.unit}) @ U<sub>dc</sub> = ${udc} V${rangeNote}${fillNote}`, font: { size: 13 }, x: 0.02, xanchor: "left" },
    margin: { l: 58, r: 10, t: 36, b: 44 },
    xaxis: axis("torque T* (N·m)", xs, xEdges),
    yaxis: axis("speed n (rpm)", ys, yEdges),
    font: FONT, paper_bgcolor: "rgba(0,0,0,0)", plot_bgcolor: "#eceff3",
  };
  const data = [trace];
  // filled cells: a hatch over the cell (its number stays readable); hover and clicks stay the heatmap's
  if (filledAt.length) {
    const hx = [];
    const hy = [];
    for (const [i, j] of filledAt) {
      const [x0, x1] = xEdges[j];
      const [y0, y1] = yEdges[i];
      hx.push(x0, x1, x1, x0, x0, null);
      hy.push(y0, y0, y1, y1, y0, null);
    }
    data.push({
      type: "scatter", mode: "lines", x: hx, y: hy, fill: "toself", fillcolor: "rgba(0,0,0,0)",
      fillpattern: { shape: "/", fgcolor: "rgba(20,20,20,0.55)", bgcolor: "rgba(0,0,0,0)", size: 7, solidity: 0.12 },
      line: { color: "rgba(20,20,20,0.75)", width: 1.5, dash: "dot" },
      hoverinfo: "skip", showlegend: false, name: "filled",
    });
  }
  // outliers of the map quality (service/maps/quality.py) get a ring; hover and clicks stay the heatmap's
  const marked = cells.filter((c) => c.quality === "outlier");
  if (marked.length) {
    data.push({
      type: "scatter", mode: "markers", x: marked.map((c) => c.torque_nm), y: marked.map((c) => c.speed_rpm),
      marker: { symbol: "circle-open", size: 30, color: "#d1495b", line: { width: 2 } },
      hoverinfo: "skip", showlegend: false, name: "outlier",
    });
  }
  // every cell carries its number where it fits (a map is read, not only looked at)
  const heat = { xs, ys, xEdges, yEdges, z, digits: q.digits, marks: null, xTicks: xs, yTicks: ys };
  return { data, layout, config: CONFIG, heat };
}

// ------------------------------------------------------------------ one result (paper Fig. 8, 9, 10)
function baseLayout(title, xTitle, yTitle, extra) {
  return Object.assign({
    title: { text: title, font: { size: 13 }, x: 0.02, xanchor: "left" },
    margin: { l: 64, r: 12, t: 36, b: 78 },
    xaxis: { title: { text: xTitle }, zeroline: false },
    yaxis: { title: { text: yTitle }, zeroline: false },
    // below the x axis title: a legend above the plot runs into the title on a narrow figure
    legend: { orientation: "h", x: 0, xanchor: "left", y: -0.22, yanchor: "top", font: { size: 10 } },
    font: FONT, paper_bgcolor: "rgba(0,0,0,0)", plot_bgcolor: "#f7f8fa",
  }, extra || {});
}

// Column `name` of trace rows, by the stored column list or at index `fallback`.
function column(rows, names, name, fallback) {
  const i = Array.isArray(names) ? names.indexOf(name) : -1;
  const k = i >= 0 ? i : fallback;
  return rows.map((row) => (Array.isArray(row) ? row[k] : null));
}

function thetaHistory(r) {
  const tr = r.traces || {};
  const rows = Array.isArray(tr.theta_history) ? tr.theta_history : [];
  if (rows.length === 0) return null;
  const cols = tr.theta_history_columns;
  return {
    t: column(rows, cols, "plant_time_s", 0),
    cos: column(rows, cols, "theta_cos", 1),
    sin: column(rows, cols, "theta_sin", 2),
    amplitude: column(rows, cols, "amplitude_fs", 3),
  };
}

// Fig. 9: theta_cos and theta_sin over plant time; null without a theta history.
export function thetaTransient(r) {
  const h = thetaHistory(r);
  if (!h) return null;
  return {
    data: [
      { x: h.t, y: h.cos, name: "θ_cos", mode: "lines+markers", line: { color: C_COS, width: 2 }, marker: { size: 5 },
        hovertemplate: "t %{x:.4f} s<br>θ_cos %{y:.5f} rad<extra></extra>" },
      { x: h.t, y: h.sin, name: "θ_sin", mode: "lines+markers", line: { color: C_SIN, width: 2 }, marker: { size: 5 },
        hovertemplate: "t %{x:.4f} s<br>θ_sin %{y:.5f} rad<extra></extra>" },
    ],
    layout: baseLayout(`Fig. 9 — θ transient (${escapeHtml(String(r.method))})`, "plant time t (s)", "θ (rad)"),
    config: CONFIG,
  };
}

// Fig. 9: the h-th amplitude per window (log), the -40 dB line and the verified residual.
export function amplitudeTransient(r) {
  const h = thetaHistory(r);
  if (!h) return null;
  const d = r.details || {};
  const u0 = r.uncompensated && Number(r.uncompensated.amplitude);
  const ts = h.t.map(Number).filter(Number.isFinite);
  const data = [{ x: h.t, y: h.amplitude, name: "|a_h| per window", mode: "lines+markers",
    line: { color: C_AFTER, width: 2 }, marker: { size: 5 },
    hovertemplate: "t %{x:.4f} s<br>|a| %{y:.3e} FS<extra></extra>" }];
  // the -40 dB level as a trace over the measured time span (data coordinates on the log axis; it
  // never stretches the time axis)
  if (u0 > 0 && ts.length) {
    data.push({ x: [Math.min(...ts), Math.max(...ts)], y: [u0 / 100, u0 / 100], name: "−40 dB", mode: "lines",
      line: { color: "#667085", width: 1, dash: "dot" }, hoverinfo: "skip" });
  }
  // the time 40 dB was reached: only when it was (null otherwise, which Number() would make 0)
  const t40 = d.time_to_40db_s;
  if (t40 !== null && t40 !== undefined && Number.isFinite(Number(t40)) && Number(t40) > 0 && u0 > 0) {
    data.push({ x: [Number(t40)], y: [u0 / 100], name: `40 dB at ${fmt(t40, 3)} s`, mode: "markers",
      marker: { symbol: "diamond", size: 9, color: "#3a9d63" },
      hovertemplate: "40 dB reached at t %{x:.4f} s<extra></extra>" });
  }
  if (r.residual && Number(r.residual.amplitude) > 0 && Number.isFinite(Number(r.plant_time_s))) {
    data.push({ x: [r.plant_time_s], y: [r.residual.amplitude], name: "verified residual", mode: "markers",
      marker: { symbol: "star", size: 11, color: "#3a9d63" },
      hovertemplate: "t %{x:.4f} s<br>residual |a| %{y:.3e} FS<extra></extra>" });
  }
  return {
    data,
    layout: baseLayout(`Fig. 9 — h-th harmonic amplitude (h = ${escapeHtml(fmt(r.harmonic_order))})`,
      "plant time t (s)", "|a_h| (FS, log)", {
        yaxis: { title: { text: "|a_h| (FS, log)" }, type: "log", exponentformat: "power" } }),
    config: CONFIG,
  };
}

// Fig. 10: spectrum of alpha (orders 1..n) before and after; null without a stored spectrum.
export function spectrum(r) {
  const tr = r.traces || {};
  const sb = Array.isArray(tr.spectrum_before) ? tr.spectrum_before : [];
  const sa = Array.isArray(tr.spectrum_after) ? tr.spectrum_after : [];
  if (sb.length === 0 && sa.length === 0) return null;
  const orders = (arr) => arr.map((_, i) => i + 1);
  const h = Number(r.harmonic_order);
  const hb = sb[h - 1];
  const ha = sa[h - 1];
  const annotations = [];
  if (Number.isFinite(h) && (hb > 0 || ha > 0)) {
    annotations.push({ x: h, y: Math.log10(Math.max(hb || 0, ha || 0)), text: `h = ${h}`, showarrow: true,
      arrowhead: 0, ax: 24, ay: -18, font: { size: 10 } });
  }
  const n = Math.max(sb.length, sa.length);
  return {
    data: [
      { type: "bar", x: orders(sb), y: sb, name: "before (θ = 0)", marker: { color: C_BEFORE },
        hovertemplate: "order %{x}<br>%{y:.3e} FS<extra>before</extra>" },
      { type: "bar", x: orders(sa), y: sa, name: "after (identified θ)", marker: { color: C_AFTER },
        hovertemplate: "order %{x}<br>%{y:.3e} FS<extra>after</extra>" },
    ],
    layout: baseLayout("Fig. 10 — spectrum of α", "electrical order k (× f_e)", "amplitude |a_k| (FS, log)", {
      barmode: "group", bargap: 0.2, annotations,
      xaxis: { title: { text: "electrical order k (× f_e)" }, tickmode: "linear", dtick: n > 12 ? 2 : 1, range: [0.4, n + 0.6] },
      yaxis: { title: { text: "amplitude |a_k| (FS, log)" }, type: "log", exponentformat: "power" },
    }),
    config: CONFIG,
  };
}

// Fig. 10: alpha over the electrical angle before and after; null without stored snippets.
export function alphaSnippets(r) {
  const tr = r.traces || {};
  const ab = tr.alpha_before || {};
  const aa = tr.alpha_after || {};
  if (!Array.isArray(ab.alpha_fs) && !Array.isArray(aa.alpha_fs)) return null;
  return {
    data: [
      { x: ab.angle_rad || [], y: ab.alpha_fs || [], name: "before (θ = 0)", mode: "lines",
        line: { color: C_BEFORE, width: 1.2 }, hovertemplate: "φ_e %{x:.3f} rad<br>α %{y:.5f} FS<extra>before</extra>" },
      { x: aa.angle_rad || [], y: aa.alpha_fs || [], name: "after (identified θ)", mode: "lines",
        line: { color: C_AFTER, width: 1.2 }, hovertemplate: "φ_e %{x:.3f} rad<br>α %{y:.5f} FS<extra>after</extra>" },
    ],
    layout: baseLayout("Fig. 10 — acceleration α, before / after", "electrical angle φ_e (rad, unwrapped)", "α (FS)"),
    config: CONFIG,
  };
}

// Fig. 8: |a_h| over the (gamma, delta) grid with the grid minimum and the affine fit;
// null unless the result has a grid search (method grid).
export function gridSurface(r) {
  const tr = r.traces || {};
  const grid = Array.isArray(tr.grid) ? tr.grid : [];
  if (grid.length === 0) return null;
  const d = r.details || {};
  const cols = tr.grid_columns;
  const g = column(grid, cols, "gamma_deg", 0).map(Number);
  const dl = column(grid, cols, "delta_deg", 1).map(Number);
  const ac = column(grid, cols, "a_c", 2).map(Number);
  const as = column(grid, cols, "a_s", 3).map(Number);
  const xs = [...new Set(g)].sort((a, b) => a - b);
  const ys = [...new Set(dl)].sort((a, b) => a - b);
  const xi = new Map(xs.map((v, i) => [v, i]));
  const yi = new Map(ys.map((v, i) => [v, i]));
  const z = ys.map(() => xs.map(() => null));
  for (let k = 0; k < g.length; k++) z[yi.get(dl[k])][xi.get(g[k])] = Math.hypot(ac[k], as[k]);
  const data = [{
    type: "contour", x: xs, y: ys, z, colorscale: "Viridis", connectgaps: false,
    contours: { coloring: "heatmap", showlines: true }, line: { width: 0.5, color: "rgba(255,255,255,0.45)" },
    colorbar: { title: { text: "|a_h| (FS)", side: "right" }, thickness: 12, len: 0.9 },
    hovertemplate: "γ %{x}°<br>δ %{y}°<br>|a_h| %{z:.3e} FS<extra></extra>", name: "|a_h|",
  }];
  const m = d.minimum;
  if (m && Number.isFinite(Number(m.gamma_deg))) {
    data.push({ type: "scatter", mode: "markers", x: [m.gamma_deg], y: [m.delta_deg], name: "grid minimum",
      marker: { symbol: "x", size: 12, color: "#ffffff", line: { width: 1.5, color: "#1d2430" } },
      hovertemplate: "grid minimum<br>γ %{x:.3f}°<br>δ %{y:.2f}°<extra></extra>" });
  }
  const f = d.fit;
  if (f && Number.isFinite(Number(f.gamma_deg))) {
    data.push({ type: "scatter", mode: "markers", x: [f.gamma_deg], y: [f.delta_deg], name: "affine fit",
      marker: { symbol: "star", size: 13, color: "#d1495b", line: { width: 1, color: "#ffffff" } },
      hovertemplate: "affine fit<br>γ %{x:.3f}°<br>δ %{y:.2f}°<extra></extra>" });
  }
  return {
    data,
    layout: baseLayout(`Fig. 8 — grid search: |a_h| over (γ, δ), ${grid.length} points`, "injection amplitude γ (°)",
      "injection phase δ (°)", {
        legend: { orientation: "h", x: 0, xanchor: "left", y: -0.18, yanchor: "top", font: { size: 10 } },
        margin: { l: 64, r: 12, t: 36, b: 78 },
      }),
    config: CONFIG,
  };
}

// ------------------------------------------------------------------ validation in the drive's LUT mode
// Suppression measured with the drive's own LUT feedforward over the finer grid (grid values and
// the midpoints between them) at one U_dc: grid points carry a ring marker, midpoints none; a
// cell that failed or was not measured stays blank with its reason on hover. Numeric axes: a
// refined map's inserted values sit at their real positions. The colour range is fixed (0…60 dB),
// so two validations (a map and its refinement) compare by colour. opts.title replaces the title.
// The grid points and midpoints of a validation (its run-up bins are judged along speed: the API lists them).
export function validationHeatmap(cells, udc, opts) {
  const mine = cells.filter((c) => c.kind !== "runup" && Number(c.operating_point.udc_v) === udc);
  const axis = (key) => [...new Set(mine.map((c) => Number(c.operating_point[key])))].sort((a, b) => a - b);
  const xs = axis("torque_nm");
  const ys = axis("speed_rpm");
  const xi = new Map(xs.map((v, i) => [v, i]));
  const yi = new Map(ys.map((v, i) => [v, i]));
  const z = ys.map(() => xs.map(() => null));
  const text = ys.map(() => xs.map(() => ""));
  const grid = { x: [], y: [] };
  for (const c of mine) {
    const op = c.operating_point;
    const i = yi.get(Number(op.speed_rpm));
    const j = xi.get(Number(op.torque_nm));
    const untrained = c.kind === "grid" && c.map_cell_status && c.map_cell_status !== "ok" ?
      ` — map cell ${escapeHtml(String(c.map_cell_status))}: no injection in the LUT` : "";
    const head = `<b>${c.kind === "grid" ? "grid point (trained)" : "midpoint (interpolated)"}</b>${untrained}<br>` +
      `T* ${fmt(op.torque_nm)} N·m<br>n ${fmt(op.speed_rpm)} rpm<br>U<sub>dc</sub> ${fmt(op.udc_v)} V<br>`;
    if (c.kind === "grid") {
      grid.x.push(xs[j]);
      grid.y.push(ys[i]);
    }
    if (c.status === "measured" && c.suppression_db !== null && c.suppression_db !== undefined) {
      z[i][j] = c.suppression_db;
      const floor = c.noise_floor_db === null || c.noise_floor_db === undefined ? "" :
        `<br>noise floor ${Number(c.noise_floor_db).toFixed(0)} dB${c.at_noise_floor ? " (at the floor: a lower bound)" : ""}`;
      text[i][j] = head + `<b>suppression = ${Number(c.suppression_db).toFixed(1)} dB</b>${floor}`;
    } else {
      text[i][j] = head + `<b>${escapeHtml(String(c.status))}</b>: ${escapeHtml(String(c.error || "no value"))}`;
    }
  }
  const heat = {
    type: "heatmap", x: xs, y: ys, z, text, hovertemplate: "%{text}<extra></extra>", hoverongaps: true,
    colorscale: "Cividis", zmin: 0, zmax: 60, xgap: 1, ygap: 1,
    colorbar: { title: { text: "dB (fixed 0…60)", side: "right" }, thickness: 12, len: 0.9 }, name: "suppression",
  };
  const marks = {
    type: "scatter", mode: "markers", x: grid.x, y: grid.y, name: "grid point (trained)", hoverinfo: "skip",
    marker: { symbol: "square-open", size: 30, color: "#d1495b", line: { width: 2 } },
  };
  const numericAxis = (title, values, edges) => ({ title: { text: title }, type: "linear", tickmode: "array",
    tickvals: values, ticktext: values.map((v) => fmt(v)), range: [edges[0][0], edges[edges.length - 1][1]],
    zeroline: false, showgrid: false, tickangle: 0, automargin: true });
  const xEdges = xs.length ? cellEdges(xs) : [[0, 1]];
  const yEdges = ys.length ? cellEdges(ys) : [[0, 1]];
  const title = (opts && opts.title) ||
    `suppression in the drive's LUT mode (dB) @ U<sub>dc</sub> = ${udc} V · ◻ grid point, else midpoint`;
  const layout = {
    title: { text: title, font: { size: 13 }, x: 0.02, xanchor: "left" },
    margin: { l: 58, r: 10, t: 36, b: 44 }, showlegend: false,
    xaxis: numericAxis("torque T* (N·m)", xs, xEdges),
    yaxis: numericAxis("speed n (rpm)", ys, yEdges),
    font: FONT, paper_bgcolor: "rgba(0,0,0,0)", plot_bgcolor: "#eceff3",
  };
  // numbers where they fit, grid values' ticks kept before the midpoints' (fit())
  const gridFirst = (values, on) => [...values.filter((v) => on.has(v)), ...values.filter((v) => !on.has(v))];
  const fitting = { xs, ys, xEdges, yEdges, z, digits: 1, marks: 1,
    xTicks: gridFirst(xs, new Set(grid.x)), yTicks: gridFirst(ys, new Set(grid.y)) };
  return { data: [heat, marks], layout, config: CONFIG, heat: fitting };
}

// ------------------------------------------------------------------ run-ups (order analysis)
const dbOf = (fs) => (fs === null || fs === undefined || !(Number(fs) > 0) ? null : 20 * Math.log10(Number(fs)));

// The Campbell diagram of a run-up's result: order (y) against speed (x), colour = level in dB of full scale.
export function campbell(result, title) {
  const z = result.amplitude.map((row) => row.map(dbOf));
  return {
    data: [{ type: "heatmap", x: result.speed_rpm, y: result.orders, z, colorscale: "Viridis", zmin: -100, zmax: 0,
      colorbar: { title: { text: "dB FS" } },
      hovertemplate: "order %{y}<br>%{x:.0f} rpm<br>%{z:.1f} dB FS<extra></extra>" }],
    // orders are categories: a numeric axis would stretch each order's row over the gap to the next one asked
    layout: baseLayout(title, "speed n (rpm)", "electrical order",
      { yaxis: { title: { text: "electrical order" }, type: "category" } }),
    config: CONFIG,
  };
}

// One order along the ramp for each run-up given ({label, result, colour}), with its bin noise floor dotted.
export function orderCut(order, runs, title) {
  const data = [];
  for (const run of runs) {
    const k = run.result.orders.indexOf(order);
    if (k < 0) continue;
    data.push({ x: run.result.speed_rpm, y: run.result.amplitude[k].map(dbOf), name: run.label, mode: "lines",
      line: { color: run.colour, width: 2 }, connectgaps: false,
      hovertemplate: `${escapeHtml(run.label)}<br>%{x:.0f} rpm<br>%{y:.1f} dB FS<extra></extra>` });
    // named but not in the legend (the card's note says dotted = noise floor): four entries run into the axis title
    data.push({ x: run.result.speed_rpm, y: run.result.noise_floor.map(dbOf), name: `${run.label}: noise floor`,
      mode: "lines", line: { color: run.colour, width: 1, dash: "dot" }, hoverinfo: "skip", showlegend: false });
  }
  return { data, layout: baseLayout(title, "speed n (rpm)", `order ${order} (dB FS)`), config: CONFIG };
}

export const ORDER_CUT_COLOURS = { before: C_BEFORE, after: C_AFTER };
