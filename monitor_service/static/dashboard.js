// Operator dashboard: reads the monitor's API with the operator key kept in sessionStorage (this tab only,
// gone when it closes; docs/monitor.md). The key may also come in the URL fragment (/dashboard#key=...): a
// fragment never reaches the server or its logs, and it is removed from the address bar at once. No external
// scripts (the deployment network may be closed): charts are drawn as inline SVG.
"use strict";

function keyFromFragment() {
  const params = new URLSearchParams(location.hash.replace(/^#/, ""));
  const key = params.get("key");
  if (key) {
    sessionStorage.setItem("jepaMonitorKey", key);
    history.replaceState(null, "", location.pathname + location.search);
  }
  return key;
}

const state = { key: keyFromFragment() || sessionStorage.getItem("jepaMonitorKey") || "", streamAbort: null };
const TRAJECTORIES_PER_TASK = 4;  // live episodes drawn for each task, most recently active first
const LIVE_LIMIT = 200;            // live episodes listed (and counted per task) at most
const SETTLED_SHOWN = 15;          // cleared or resolved alerts listed below the open and acknowledged ones

function h(tag, attrs = {}, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "onclick") el.addEventListener("click", v);
    else el.setAttribute(k, v);
  }
  for (const c of children) el.append(c instanceof Node ? c : document.createTextNode(c ?? ""));
  return el;
}

function fmt(x, digits = 3) {
  return x === null || x === undefined ? "\u221e" : Number(x).toFixed(digits);
}

async function api(path, options = {}) {
  const res = await fetch(path, { ...options, headers: { "X-API-Key": state.key, "Content-Type": "application/json", ...(options.headers || {}) } });
  if (!res.ok) throw new Error(`${res.status} ${(await res.json().catch(() => ({}))).detail || res.statusText}`);
  return res.json();
}

function setStatus(text) { document.getElementById("status").textContent = text; }

function svg(tag, attrs) {
  const el = document.createElementNS("http://www.w3.org/2000/svg", tag);
  for (const [k, v] of Object.entries(attrs)) el.setAttribute(k, v);
  return el;
}

function text(x, y, content, attrs = {}) {
  const el = svg("text", { x, y, "font-size": 11, ...attrs });
  el.textContent = content;
  return el;
}

// A framed plot area with a title above it and labelled axes; returns [root, x(frac), y(frac)].
function frame(cls, data, title, xlabel, ylabel, W = 320, H = 240) {
  const L = 48, R = 12, T = 30, B = 40;
  const root = svg("svg", { width: W, height: H, class: cls, ...data });
  root.append(svg("rect", { x: L, y: T, width: W - L - R, height: H - T - B, fill: "none", stroke: "#999" }));
  root.append(text(6, 16, title, { class: "title", "font-weight": "bold" }));
  root.append(text(L + (W - L - R) / 2, H - 8, xlabel, { "text-anchor": "middle", class: "xlabel" }));
  const y = text(14, T + (H - T - B) / 2, ylabel, { "text-anchor": "middle", class: "ylabel" });
  y.setAttribute("transform", `rotate(-90 14 ${T + (H - T - B) / 2})`);
  root.append(y);
  return [root, (f) => L + f * (W - L - R), (f) => H - B - f * (H - T - B)];
}

function ticks(root, X, Y, lo, hi, axis, format) {
  for (const f of [0, 0.5, 1]) {
    const v = lo + f * (hi - lo);
    if (axis === "x") root.append(text(X(f), Y(0) + 13, format(v), { "text-anchor": "middle" }));
    else root.append(text(X(0) - 4, Y(f) + 4, format(v), { "text-anchor": "end" }));
  }
}

function rocChart(task, roc, auroc) {
  const [root, X, Y] = frame("roc", { "data-task": task }, `ROC ${task} (AUROC ${fmt(auroc)})`,
    "false-positive rate", "true-positive rate", 280, 260);
  root.append(svg("line", { x1: X(0), y1: Y(0), x2: X(1), y2: Y(1), stroke: "#ccc", "stroke-dasharray": "4" }));
  const pts = roc.fpr.map((f, i) => `${X(f)},${Y(roc.tpr[i])}`).join(" ");
  root.append(svg("polyline", { points: pts, fill: "none", stroke: "#1f3b57", "stroke-width": 2 }));
  ticks(root, X, Y, 0, 1, "x", (v) => v.toFixed(1));
  ticks(root, X, Y, 0, 1, "y", (v) => v.toFixed(1));
  return root;
}

function histogramChart(task, hist) {
  const [root, X, Y] = frame("histogram", { "data-task": task }, `Early score ${task}: successes / failures`,
    "early score: median NMSE of the first 5 decisions (log scale)", "episodes", 380, 260);
  const n = hist.success.length;
  const max = Math.max(1, ...hist.success, ...hist.failure);
  const bw = 1 / n;
  hist.success.forEach((c, i) => root.append(svg("rect", { x: X(i * bw), y: Y(c / max), width: X(bw / 2) - X(0), height: Y(0) - Y(c / max), fill: "#4caf50" })));
  hist.failure.forEach((c, i) => root.append(svg("rect", { x: X(i * bw + bw / 2), y: Y(c / max), width: X(bw / 2) - X(0), height: Y(0) - Y(c / max), fill: "#e53935" })));
  ticks(root, X, Y, Math.log10(hist.edges[0]), Math.log10(hist.edges[hist.edges.length - 1]), "x", (v) => `1e${v.toFixed(1)}`);
  ticks(root, X, Y, 0, max, "y", (v) => v.toFixed(0));
  return root;
}

// One live episode: the rule's statistic after each scored decision (by the env step at which it became
// known) against its decision index's threshold (dashed); red points are above it, hollow points lie beyond the
// calibrated length (no guarantee there).
function trajectoryChart(detail, signal) {
  const pts = detail.signal_risk[signal];
  const values = pts.map((p) => p.value).concat(pts.map((p) => p.threshold));
  let lo = Math.min(...values), hi = Math.max(...values);
  if (hi - lo < 1e-9) { lo -= 1; hi += 1; }
  const pad = 0.08 * (hi - lo);
  lo -= pad; hi += pad;
  const x0 = 0, x1 = Math.max(1, ...pts.map((p) => p.known_at));
  const title = `${detail.id} (${detail.task}, ${signal}, ${detail.rule} rule)`;
  const [root, X, Y] = frame("trajectory", { "data-episode": detail.id, "data-signal": signal, "data-task": detail.task },
    title, "env step",
    detail.rule === "band" ? `${signal}: band z-score, running median` : `${signal}, running median`, 340, 220);
  const fx = (s) => X((s - x0) / (x1 - x0)), fy = (v) => Y((v - lo) / (hi - lo));
  root.append(svg("polyline", { points: pts.map((p) => `${fx(p.known_at)},${fy(p.threshold)}`).join(" "),
    fill: "none", stroke: "#b00020", "stroke-dasharray": "5", class: "threshold" }));
  root.append(svg("polyline", { points: pts.map((p) => `${fx(p.known_at)},${fy(p.value)}`).join(" "), fill: "none",
    stroke: "#1f3b57", "stroke-width": 2, class: "risk" }));
  for (const p of pts) {
    const color = p.value > p.threshold ? "#b00020" : "#1f3b57";
    root.append(svg("circle", { cx: fx(p.known_at), cy: fy(p.value), r: 2.5, stroke: color,
      fill: p.beyond_calibration ? "white" : color, class: p.beyond_calibration ? "beyond" : "" }));
  }
  ticks(root, X, Y, x0, x1, "x", (v) => v.toFixed(0));
  ticks(root, X, Y, lo, hi, "y", (v) => v.toPrecision(2));
  return root;
}

// Which signals alert and how, e.g. "stac" or "fiper(stac+nmse)" (a calibration before named signals: nmse).
function detectorName(result) {
  const spec = result.detector ? result.detector.spec : { signals: ["nmse"], combination: "single" };
  return spec.combination === "single" ? spec.signals[0] : `${spec.combination}(${spec.signals.join("+")})`;
}

async function refresh() {
  // every alert waiting for someone, then the most recent settled ones (all: GET /v1/alerts)
  const [report, open, acked, resolved, cleared, episodes] = await Promise.all([
    api("/v1/report"), api("/v1/alerts?state=open&limit=1000"), api("/v1/alerts?state=acknowledged&limit=1000"),
    api("/v1/alerts?state=resolved&limit=" + SETTLED_SHOWN), api("/v1/alerts?state=cleared&limit=" + SETTLED_SHOWN),
    api(`/v1/episodes?live=true&limit=${LIVE_LIMIT}`),
  ]);
  const settled = resolved.concat(cleared).sort((a, b) => b.id - a.id).slice(0, SETTLED_SHOWN);
  const alerts = open.concat(acked, settled);
  // each task's own live episodes, so that a busy task hides neither another's count nor its trajectories
  const tasks = report.tasks.filter((c) => !c.checkpoint).map((c) => c.task);
  const liveOf = Object.fromEntries(await Promise.all(tasks.map(async (t) =>
    [t, await api(`/v1/episodes?live=true&limit=${LIVE_LIMIT}&task=${encodeURIComponent(t)}`)])));
  const tbody = document.querySelector("#tasks tbody");
  tbody.replaceChildren();
  const charts = document.getElementById("charts");
  charts.replaceChildren();
  for (const c of report.tasks) {
    if (c.checkpoint) continue;
    const live = liveOf[c.task];
    const over = live.filter((e) => e.risk_score !== null && e.risk_score > e.risk_threshold).length;
    const openAlerts = alerts.filter((a) => a.task === c.task && (a.state === "open" || a.state === "acknowledged")).length;
    const r = c.result;
    // a length bin is promised (alpha there) unless the calibration held too few successes of that length
    const bins = r.rule.regimes || [];
    const promised = bins.filter((g) => g.promise !== false).map((g) => `${g.lo}-${g.hi}`).join(", ");
    const unpromised = bins.filter((g) => g.promise === false).map((g) => `${g.lo}-${g.hi} (${g.n} successes)`).join(", ");
    const promiseText = r.alpha === undefined ? "-" :
      (promised ? `${r.alpha} in each of ${promised} decisions` : `${r.alpha} on average over all lengths only`) +
      (unpromised ? `; no promise at ${unpromised}: too few held-out successes that long` : "");
    tbody.append(h("tr", { "data-task": c.task },
      h("td", {}, c.task), h("td", {}, `${fmt(r.auroc)} [${fmt(r.auroc_ci_low)}, ${fmt(r.auroc_ci_high)}]`),
      h("td", {}, fmt(r.average_precision)), h("td", {}, fmt(r.permutation_p, 4)),
      h("td", { class: "detector" }, `${detectorName(r)}, ${c.rule}: up to ${fmt(c.threshold, 4)}`),
      h("td", { class: unpromised ? "regimes no-promise" : "regimes" }, promiseText),
      h("td", {}, live.length >= LIVE_LIMIT ? `${LIVE_LIMIT}+` : String(live.length)),
      h("td", { class: over ? "risk-high" : "" }, String(over)),
      h("td", {}, String(openAlerts))));
    const box = h("div", { class: "chart" });
    box.append(rocChart(c.task, r.roc, r.auroc), histogramChart(c.task, r.histogram));
    charts.append(box);
  }
  document.getElementById("pooled").textContent = report.pooled.auroc === null ? "" :
    `Pooled AUROC ${fmt(report.pooled.auroc)} over ${report.pooled.n_episodes} episodes. ${report.pooled.warning}`;
  document.getElementById("uncalibrated").textContent = report.uncalibrated_tasks.length ?
    `Uncalibrated tasks (no alerts): ${report.uncalibrated_tasks.join(", ")}` : "";

  const abody = document.querySelector("#alerts tbody");
  abody.replaceChildren();
  document.getElementById("alerts-shown").textContent = `${open.length} open, ${acked.length} acknowledged, ` +
    `then the ${settled.length} most recent cleared or resolved (every alert: GET /v1/alerts).`;
  for (const a of alerts) {
    // Only an open alert waits for someone; acknowledged, cleared and resolved ones show what happened.
    const action = a.state === "open" ?
      h("button", { class: "ack", "data-alert": a.id, onclick: () => acknowledge(a.id) }, "Acknowledge") : "";
    const stateText = a.state === "resolved" ? `resolved: ${a.resolution === "success" ? "success (false alert)" : "failure"}` : a.state;
    abody.append(h("tr", { class: a.state, "data-alert": a.id },
      h("td", {}, String(a.id)), h("td", {}, a.task), h("td", {}, a.robot), h("td", {}, a.episode_id),
      h("td", {}, String(a.step)), h("td", {}, `${fmt(a.score, 4)} / ${fmt(a.threshold, 4)}`),
      h("td", { class: "state", title: a.note }, stateText + (a.beyond_calibration ? " (beyond the calibrated length)" : "") +
        (a.no_promise ? " (no false-alert promise at this episode's length: too few calibration successes that long)" : "")),
      h("td", {}, a.acknowledged_at ? a.acknowledged_by : "no"), h("td", {}, action)));
  }

  const ebody = document.querySelector("#episodes tbody");
  ebody.replaceChildren();
  for (const e of episodes) {
    const known = e.risk_score !== null && e.risk_threshold !== null;
    const early = e.early_score === null ? "-" : fmt(e.early_score, 4) +
      (e.early_revisions ? ` (revised ${e.early_revisions}x)` : "");
    const gaps = e.gaps || e.late_decisions ? `${e.gaps} missing${e.gap_steps.length ? " at " + e.gap_steps.slice(0, 5).join(", ") : ""}` +
      (e.late_decisions ? `, ${e.late_decisions} late` : "") : "0";
    ebody.append(h("tr", { "data-episode": e.id },
      h("td", {}, e.id), h("td", {}, e.task), h("td", {}, e.robot), h("td", {}, `${e.n_decisions} (${e.n_scored})`),
      h("td", { class: e.gaps ? "gaps risk-high" : "gaps" }, gaps),
      h("td", { class: "early" }, early),
      h("td", {}, e.running_score === null ? "-" : fmt(e.running_score, 4)),
      h("td", { class: known && e.risk_score > e.risk_threshold ? "risk-high" : "" },
        known ? `${fmt(e.risk_score, 3)} / ${fmt(e.risk_threshold, 3)}` +
          (e.beyond_calibration ? ` (beyond ${e.calibrated_decisions} calibrated decisions)` : "") : "-"),
      h("td", {}, e.alert_note)));
  }

  // every task's charts are built first and swapped in at once: a reader never sees a half-drawn section
  const details = await Promise.all(tasks.map((t) => Promise.all(liveOf[t].slice(0, TRAJECTORIES_PER_TASK).map((e) =>
    api(`/v1/episodes/${encodeURIComponent(e.id)}`)))));
  const drawn = [];
  tasks.forEach((t, i) => {
    const box = h("div", { class: "chart", "data-task": t });
    for (const d of details[i]) {
      for (const [signal, pts] of Object.entries(d.signal_risk || {})) {
        if (d.rule !== null && pts.length) box.append(trajectoryChart(d, signal));
      }
    }
    if (box.children.length) drawn.push(h("h3", {}, t), box);
  });
  document.getElementById("trajectories").replaceChildren(...(drawn.length ? drawn :
    [h("p", {}, "No live episode has a scored decision under a usable calibration.")]));
}

async function acknowledge(id) {
  try {
    await api(`/v1/alerts/${id}/ack`, { method: "POST", body: JSON.stringify({ note: "acknowledged from dashboard" }) });
    await refresh();
    setStatus(`acknowledged alert ${id}`);
  } catch (err) { setStatus(`acknowledge failed: ${err.message}`); }
}

// Server-sent events read with fetch so the key travels in a header, not in the URL.
async function stream() {
  if (state.streamAbort) state.streamAbort.abort();
  state.streamAbort = new AbortController();
  try {
    const res = await fetch("/v1/alerts/stream", { headers: { "X-API-Key": state.key }, signal: state.streamAbort.signal });
    const reader = res.body.getReader();
    const decoder = new TextDecoder();
    let buf = "";
    for (;;) {
      const { value, done } = await reader.read();
      if (done) break;
      buf += decoder.decode(value, { stream: true });
      let i;
      while ((i = buf.indexOf("\n\n")) >= 0) {
        const block = buf.slice(0, i);
        buf = buf.slice(i + 2);
        if (block.includes("event: alert")) refresh().catch((e) => setStatus(e.message));
      }
    }
  } catch (err) {
    if (err.name === "AbortError") return;
  }
  setTimeout(stream, 2000);
}

async function connect(ev) {
  if (ev) ev.preventDefault();
  state.key = document.getElementById("api-key").value || state.key;
  sessionStorage.setItem("jepaMonitorKey", state.key);
  try {
    await refresh();
    setStatus("connected");
    stream();
  } catch (err) { setStatus(`error: ${err.message}`); }
}

document.getElementById("key-form").addEventListener("submit", connect);
document.getElementById("api-key").value = state.key;
setInterval(() => { if (state.key) refresh().catch((e) => setStatus(`error: ${e.message}`)); }, 3000);
if (state.key) connect();
