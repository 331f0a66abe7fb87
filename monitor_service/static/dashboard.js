// Operator dashboard: reads the monitor's API with the operator key kept in localStorage.
// No external scripts (the deployment network may be closed): charts are drawn as inline SVG.
"use strict";

const state = { key: localStorage.getItem("jepaMonitorKey") || "", streamAbort: null };

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

function rocChart(task, roc, auroc) {
  const W = 220, P = 25, S = W - 2 * P;
  const root = svg("svg", { width: W, height: W, "data-task": task, class: "roc" });
  root.append(svg("rect", { x: P, y: P, width: S, height: S, fill: "none", stroke: "#999" }));
  root.append(svg("line", { x1: P, y1: P + S, x2: P + S, y2: P, stroke: "#ccc", "stroke-dasharray": "4" }));
  const pts = roc.fpr.map((f, i) => `${P + f * S},${P + S - roc.tpr[i] * S}`).join(" ");
  root.append(svg("polyline", { points: pts, fill: "none", stroke: "#1f3b57", "stroke-width": 2 }));
  const label = svg("text", { x: P, y: 15, "font-size": 11 });
  label.textContent = `ROC ${task} (AUROC ${fmt(auroc)})`;
  root.append(label);
  return root;
}

function histogramChart(task, hist, threshold) {
  const W = 300, H = 220, P = 25;
  const root = svg("svg", { width: W, height: H, "data-task": task, class: "histogram" });
  const n = hist.success.length;
  const max = Math.max(1, ...hist.success, ...hist.failure);
  const bw = (W - 2 * P) / n;
  hist.success.forEach((c, i) => root.append(svg("rect", { x: P + i * bw, y: H - P - (c / max) * (H - 2 * P), width: bw / 2, height: (c / max) * (H - 2 * P), fill: "#4caf50" })));
  hist.failure.forEach((c, i) => root.append(svg("rect", { x: P + i * bw + bw / 2, y: H - P - (c / max) * (H - 2 * P), width: bw / 2, height: (c / max) * (H - 2 * P), fill: "#e53935" })));
  if (threshold !== null && threshold !== undefined) {
    const lo = Math.log(hist.edges[0]), hi = Math.log(hist.edges[hist.edges.length - 1]);
    if (hi > lo && threshold > 0) {
      const x = P + ((Math.log(threshold) - lo) / (hi - lo)) * (W - 2 * P);
      root.append(svg("line", { x1: x, y1: P, x2: x, y2: H - P, stroke: "#000", "stroke-dasharray": "3" }));
    }
  }
  const label = svg("text", { x: P, y: 15, "font-size": 11 });
  label.textContent = `early NMSE ${task}: success (green) / failure (red), log bins`;
  root.append(label);
  return root;
}

async function refresh() {
  const [report, alerts, episodes] = await Promise.all([
    api("/v1/report"), api("/v1/alerts?limit=100"), api("/v1/episodes?live=true&limit=200"),
  ]);
  const thresholds = {};
  const tbody = document.querySelector("#tasks tbody");
  tbody.replaceChildren();
  const charts = document.getElementById("charts");
  charts.replaceChildren();
  for (const c of report.tasks) {
    if (c.checkpoint) continue;
    thresholds[c.task] = c.threshold;
    const live = episodes.filter((e) => e.task === c.task);
    const risks = live.map((e) => (e.running_score !== null && c.threshold ? e.running_score / c.threshold : null)).filter((r) => r !== null);
    const openAlerts = alerts.filter((a) => a.task === c.task && a.state === "open").length;
    const r = c.result;
    tbody.append(h("tr", { "data-task": c.task },
      h("td", {}, c.task), h("td", {}, `${fmt(r.auroc)} [${fmt(r.auroc_ci_low)}, ${fmt(r.auroc_ci_high)}]`),
      h("td", {}, fmt(r.average_precision)), h("td", {}, fmt(r.permutation_p, 4)),
      h("td", {}, `${fmt(c.threshold, 4)} (${c.threshold_rule})`), h("td", {}, String(live.length)),
      h("td", { class: risks.some((x) => x > 1) ? "risk-high" : "" }, risks.length ? fmt(Math.max(...risks), 2) : "-"),
      h("td", {}, String(openAlerts))));
    const box = h("div", { class: "chart" });
    box.append(rocChart(c.task, r.roc, r.auroc), histogramChart(c.task, r.histogram, c.threshold));
    charts.append(box);
  }
  document.getElementById("pooled").textContent = report.pooled.auroc === null ? "" :
    `Pooled AUROC ${fmt(report.pooled.auroc)} over ${report.pooled.n_episodes} episodes. ${report.pooled.warning}`;
  document.getElementById("uncalibrated").textContent = report.uncalibrated_tasks.length ?
    `Uncalibrated tasks (no alerts): ${report.uncalibrated_tasks.join(", ")}` : "";

  const abody = document.querySelector("#alerts tbody");
  abody.replaceChildren();
  for (const a of alerts) {
    const ack = a.acknowledged_at ? `${a.acknowledged_by}` :
      h("button", { class: "ack", "data-alert": a.id, onclick: () => acknowledge(a.id) }, "Acknowledge");
    abody.append(h("tr", { class: a.state, "data-alert": a.id },
      h("td", {}, String(a.id)), h("td", {}, a.task), h("td", {}, a.robot), h("td", {}, a.episode_id),
      h("td", {}, String(a.step)), h("td", {}, `${fmt(a.score, 4)} / ${fmt(a.threshold, 4)}`), h("td", {}, a.state),
      h("td", {}, a.acknowledged_at ? a.acknowledged_by : "no"), h("td", {}, a.acknowledged_at ? "" : ack)));
  }

  const ebody = document.querySelector("#episodes tbody");
  ebody.replaceChildren();
  for (const e of episodes) {
    const thr = thresholds[e.task];
    const risk = e.running_score !== null && thr ? e.running_score / thr : null;
    ebody.append(h("tr", { "data-episode": e.id },
      h("td", {}, e.id), h("td", {}, e.task), h("td", {}, e.robot), h("td", {}, `${e.n_decisions} (${e.n_scored})`),
      h("td", {}, e.early_score === null ? "-" : fmt(e.early_score, 4)),
      h("td", {}, e.running_score === null ? "-" : fmt(e.running_score, 4)),
      h("td", { class: risk > 1 ? "risk-high" : "" }, risk === null ? "-" : fmt(risk, 2)), h("td", {}, e.alert_note)));
  }
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
  localStorage.setItem("jepaMonitorKey", state.key);
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
