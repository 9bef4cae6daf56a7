// Panel (2d): run-ups. The form starts one (POST /runups, operator); the list holds the newest (GET /runups);
// the chosen one is drawn as its Campbell diagram (every order against speed) and the calibrated order's cut
// along the ramp, before (injection off) and after (the drive's LUT or a fixed theta) on one plot: a run-up is
// paired with the newest one of the other kind at the same torque and U_dc.
import * as api from "../api.js";
import { $, el, setText, showMsg } from "../dom.js";
import { fmt, shortTime } from "../format.js";
import * as figures from "../figures.js";
import * as benchChoice from "../bench-choice.js";
import { parseList } from "../grid-form.js";

const LIST_LIMIT = 20;
let runups = [];       // GET /runups, newest first
let chosenId = null;   // the run-up drawn
let cutOrder = null;   // the order whose cut is drawn (null: the run-up's harmonic order)

export function init() {
  $("runup-form").addEventListener("submit", submit);
  $("runup-select").addEventListener("change", () => {
    chosenId = Number($("runup-select").value) || null;
    draw();
  });
  $("runup-cut-order").addEventListener("change", () => {
    cutOrder = Number($("runup-cut-order").value) || null;
    draw();
  });
}

function request() {
  const v = (id) => $(id).value.trim();
  const body = {
    torque_nm: Number(v("runup-torque")),
    udc_v: Number(v("runup-udc")),
    speed_rpm: [Number(v("runup-from")), Number(v("runup-to"))],
    rate_rpm_per_s: Number(v("runup-rate")),
    direction: v("runup-direction"),
    injection: v("runup-injection"),
  };
  if (v("runup-decoupling") !== "") body.decoupling = v("runup-decoupling") === "on";
  if (v("runup-orders") !== "") {  // empty: the harmonic order and the survey of orders 1..48
    const orders = parseList(v("runup-orders"), "orders");
    if (orders.error) return { error: orders.error };
    body.orders = orders.vals;
  }
  return { body: benchChoice.withBench(body) };
}

async function submit(ev) {
  ev.preventDefault();
  showMsg("runup-error", null);
  const { body, error } = request();
  if (error) {
    showMsg("runup-error", [error], "Run-up not sent");
    return;
  }
  try {
    const job = await api.post("/runups", body);
    chosenId = job.id;
    await reload();
  } catch (e) {
    showMsg("runup-error", api.errorLines(e), "Run-up refused");
  }
}

export async function reload() {
  try {
    runups = await api.get(`/runups?limit=${LIST_LIMIT}`);
  } catch (_) {
    return; // the next event or reload brings it
  }
  const select = $("runup-select");
  select.replaceChildren(...runups.map((j) => el("option", { value: String(j.id) }, label(j))));
  if (chosenId === null && runups.length) chosenId = runups[0].id;
  if (chosenId !== null) select.value = String(chosenId);
  draw();
}

// SSE job.state: a run-up that changed state is shown as it now is.
export function onJobState(p) {
  if (p.kind === "runup") reload();
}

function label(j) {
  const r = j.request;
  return `#${j.id} · ${j.state} · ${fmt(r.torque_nm)} N·m · ${fmt(r.speed_rpm[0])}→${fmt(r.speed_rpm[1])} rpm · ` +
    `injection ${r.injection}`;
}

// The run-up of the other kind (off <-> lut/theta) at the same torque and U_dc, the newest done one.
function counterpart(job) {
  const before = job.request.injection === "off";
  return runups.find((j) => j.id !== job.id && j.state === "done" && j.result && j.result.state === "done" &&
    (j.request.injection === "off") !== before && j.request.torque_nm === job.request.torque_nm &&
    j.request.udc_v === job.request.udc_v) || null;
}

function draw() {
  const job = runups.find((j) => j.id === chosenId);
  const box = $("runups");
  box.dataset.drawn = "";
  if (!job) {
    setText("runup-meta", runups.length ? "" : "No run-up yet.");
    return;
  }
  const result = job.result;
  if (job.state !== "done" || !result || result.state !== "done") {
    setText("runup-meta", `run-up ${job.id}: ${job.state}${job.error ? " — " + job.error : ""}`);
    figures.purge("plot-campbell");
    figures.purge("plot-order-cut");
    return;
  }
  // the orders to pick for compensation (result.orders_above, largest first)
  const above = (result.orders_above || []).map((p) => p.order).join(", ") || "none";
  setText("runup-meta", `run-up ${job.id} · ${shortTime(job.finished_at)} · ${result.speed_rpm.length} bins · ` +
    `plant ${fmt(result.plant_time_s, 1)} s · torque actual ${fmt(result.torque_actual_nm, 2)} N·m · ` +
    `orders ${fmt(result.list_above_db, 0)} dB above the floor: ${above}`);
  if (!figures.plotlyLoaded()) return;
  figures.draw("plot-campbell", figures.campbell(result, `Campbell diagram — run-up ${job.id}`));
  const other = counterpart(job);
  const pair = [job, other].filter(Boolean).map((j) => {
    const before = j.request.injection === "off";
    return { label: `${before ? "before" : "after"} (injection ${j.request.injection}, run-up ${j.id})`,
      result: j.result, colour: figures.ORDER_CUT_COLOURS[before ? "before" : "after"], before };
  }).sort((a, b) => Number(b.before) - Number(a.before));
  // the order cut: the harmonic order unless another of the run-up's orders is chosen (each order of a LUT)
  const orders = result.orders || [result.harmonic_order];
  const order = orders.includes(cutOrder) ? cutOrder : result.harmonic_order;
  const cutSelect = $("runup-cut-order");
  cutSelect.replaceChildren(...orders.map((h) => el("option", { value: String(h) }, String(h))));
  cutSelect.value = String(order);
  figures.draw("plot-order-cut", figures.orderCut(order, pair, `order ${order} along the ramp — before / after`));
  box.dataset.drawn = String(pair.length);
}
