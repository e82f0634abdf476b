// The line performance page: Pareto of downtime by root cause, the loss waterfall of a shift,
// the OEE trend (Chart.js, served from /static/vendor) and the episodes; from /api/line every 5 s.
// An ES module like the other screens' (app/): their escaping and 24-hour times, from app/dom.js.
import { esc, fmtTime as clock } from "./app/dom.js";

const $ = (sel) => document.querySelector(sel);
const REFRESH_MS = 5000;
const charts = {};
let shiftChoice = "current";

function pct(x) { return x === null || x === undefined ? "–" : `${(100 * x).toFixed(1)}%`; }
function dur(s) {
  const sign = s < 0 ? "-" : "";
  s = Math.abs(s);
  const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60), sec = s % 60;
  return `${sign}${h}:${String(m).padStart(2, "0")}:${sec.toFixed(1).padStart(4, "0")}`;
}

// the header of the other screens: the cell's title, Overview, a tab per unit, Alarms, Line
async function header() {
  try {
    const r = await fetch("/api/config", { headers: { Accept: "application/json" } });
    if (!r.ok) return;
    const cfg = await r.json();
    $("#title").textContent = cfg.title || "PackML HMI";
    document.title = `Line · ${cfg.title || "PackML HMI"}`;
    $("#nav").innerHTML = [`<a href="/#/overview">Overview</a>`]
      .concat(cfg.units.map((u) => `<a href="/#/unit/${encodeURIComponent(u.name)}">${esc(u.name)}</a>`))
      .concat([`<a href="/#/alarms">Alarms</a>`]).join("");
  } catch (e) {
    // the tabs stay as the page came: Overview and Alarms
  }
}

function chart(id, config) {
  if (charts[id]) {
    charts[id].data = config.data;
    charts[id].update("none");
    return charts[id];
  }
  config.options = Object.assign({ responsive: true, maintainAspectRatio: false, animation: false }, config.options || {});
  charts[id] = new window.Chart($(`#${id}`), config);
  return charts[id];
}

function kpis(data) {
  const line = data.shift.scopes[0];
  $("#kpis").innerHTML =
    `<div class="kpi-scope">${esc(data.shift.window)} · elapsed ${dur(line.elapsed)}</div>` +
    [["OEE", line.oee], ["Availability", line.availability], ["Performance", line.performance], ["Quality", line.quality]]
      .map(([k, v]) => `<div class="kpi"><div class="kpi-value" data-kpi="${k}">${pct(v)}</div><div class="kpi-label">${k}</div></div>`).join("");
}

function current(data) {
  const e = data.current || data.episodes[0];
  const box = $("#current");
  if (!e) {
    box.className = "card line-episode closed";
    box.innerHTML = `<div class="ep-title">No stop episode yet</div>`;
    return;
  }
  box.className = `card line-episode ${e.open ? "open" : "closed"}`;
  box.innerHTML = `<div class="ep-title" id="episode-title">${e.open ? "Line stopped" : "Last stop"} · episode ${e.id}</div>
    <dl><dt>Root cause</dt><dd id="episode-root">${esc(e.root_unit)}</dd>
    <dt>Reason</dt><dd id="episode-reason">${esc(e.reason)}</dd>
    <dt>Bucket</dt><dd>${esc(e.bucket.replace("_", " "))}</dd>
    <dt>Since</dt><dd>${clock(e.start)} (${dur(e.duration)}${e.open ? ", open" : ""})</dd>
    <dt>Affected</dt><dd>${e.affected.map((a) => `${esc(a.unit)} (${esc(a.how)})`).join(", ")}</dd></dl>`;
}

function pareto(data) {
  const by = new Map();
  for (const e of data.episodes) {
    const key = `${e.root_unit}: ${e.reason}`;
    by.set(key, (by.get(key) || 0) + e.duration);
  }
  const rows = [...by.entries()].sort((a, b) => b[1] - a[1]);
  const total = rows.reduce((s, r) => s + r[1], 0);
  let acc = 0;
  const cumulative = rows.map((r) => { acc += r[1]; return total ? (100 * acc) / total : 0; });
  $("#pareto-note").textContent = `${data.episodes.length} episodes, ${dur(total)}`;
  chart("pareto", {
    type: "bar",
    data: {
      labels: rows.map((r) => r[0]),
      datasets: [
        { type: "bar", label: "downtime (min)", data: rows.map((r) => r[1] / 60), backgroundColor: "#c62828", yAxisID: "y" },
        { type: "line", label: "cumulative %", data: cumulative, borderColor: "#1f6feb", backgroundColor: "#1f6feb", yAxisID: "pct" },
      ],
    },
    options: { scales: { y: { beginAtZero: true, title: { display: true, text: "minutes" } },
                         pct: { position: "right", min: 0, max: 100, grid: { drawOnChartArea: false } } } },
  });
}

const PLANNED_COLORS = { "planned stop": "#8a96a3", changeover: "#5b7fa6" };

function waterfall(data) {
  const s = data.shift.scopes[0];
  const steps = [["planned stop", s.planned_stop], ["changeover", s.changeover], ["unplanned stop", s.unplanned_stop], ["blocked", s.blocked],
                 ["starved", s.starved], ["held", s.held], ["speed loss", s.speed_loss], ["quality loss", s.quality_loss]];
  const labels = ["elapsed"], bars = [[0, s.elapsed / 60]], colors = ["#52606d"];
  let level = s.elapsed;
  for (const [name, value] of steps) {
    labels.push(name);
    bars.push([(level - value) / 60, level / 60]);
    colors.push(PLANNED_COLORS[name] || "#e08600");  // planned time is not a loss: not orange
    level -= value;
  }
  labels.push("productive");
  bars.push([0, s.productive / 60]);
  colors.push("#2e7d32");
  chart("waterfall", {
    type: "bar",
    data: { labels, datasets: [{ label: "minutes", data: bars, backgroundColor: colors }] },
    options: { plugins: { legend: { display: false } }, scales: { y: { title: { display: true, text: "minutes" } } } },
  });
}

function trend(data) {
  chart("trend", {
    type: "line",
    data: {
      labels: data.trend.map((w) => new Date(w.end * 1000).toLocaleTimeString([], { hour: "2-digit", minute: "2-digit", hour12: false })),
      datasets: ["oee", "availability", "performance", "quality"].map((k, i) => ({
        label: k, data: data.trend.map((w) => (w.scopes[0].elapsed > 0 && w.scopes[0][k] !== null ? 100 * w.scopes[0][k] : null)),
        borderColor: ["#1d2733", "#1565c0", "#e08600", "#2e7d32"][i], borderWidth: k === "oee" ? 3 : 1.5, spanGaps: true,
      })),
    },
    options: { scales: { y: { min: 0, suggestedMax: 100, title: { display: true, text: "%" } } } },
  });
}

function episodes(data) {
  $("#episodes-note").textContent = `${data.episodes.length} of ${data.episodes_total}`;
  $("#episodes tbody").innerHTML = data.episodes.map((e) => `<tr data-episode="${e.id}">
    <td class="num">${e.id}</td><td>${clock(e.start)}</td><td class="num">${dur(e.duration)}${e.open ? " (open)" : ""}</td>
    <td>${esc(e.root_unit)}</td><td>${esc(e.reason)}</td>
    <td>${e.affected.map((a) => `${esc(a.unit)} (${esc(a.how)})`).join(", ")}</td></tr>`).join("");
}

function losses(data) {
  const cols = ["elapsed", "planned_stop", "changeover", "unplanned_stop", "blocked", "starved", "held", "running", "speed_loss", "quality_loss", "productive"];
  $("#losses thead").innerHTML = `<tr><th>Scope</th>${cols.map((c) => `<th class="num">${c.replace("_", " ")}</th>`).join("")}<th class="num">OEE</th></tr>`;
  $("#losses tbody").innerHTML = data.shift.scopes.map((s) => `<tr data-scope="${esc(s.scope)}"><td>${esc(s.scope)}</td>${cols.map((c) => `<td class="num">${dur(s[c])}</td>`).join("")}<td class="num">${pct(s.oee)}</td></tr>`).join("");
}

function shifts(data) {
  const select = $("#shift");
  const options = ["current", ...data.shifts.map((w) => w.window.replace(/^shift:/, ""))];
  const unique = [...new Set(options)];
  if (select.dataset.options !== unique.join("|")) {
    select.innerHTML = unique.map((k) => `<option value="${esc(k)}">${k === "current" ? "current shift" : esc(k)}</option>`).join("");
    select.dataset.options = unique.join("|");
    select.value = shiftChoice;
  }
}

async function refresh() {
  try {
    const r = await fetch(`/api/line?shift=${encodeURIComponent(shiftChoice)}`, { headers: { Accept: "application/json" } });
    const data = await r.json();
    if (!r.ok) throw new Error(data.message || r.statusText);
    $("#title").textContent = `Line ${data.cell}`;
    shifts(data);
    kpis(data);
    current(data);
    episodes(data);
    losses(data);
    if (window.Chart) {
      pareto(data);
      waterfall(data);
      trend(data);
    }
    $("#line-lamp").className = "lamp on-ok";
    $("#line-updated").textContent = `updated ${new Date().toLocaleTimeString([], { hour12: false })}`;
    document.body.dataset.loaded = "1";
  } catch (err) {
    $("#line-lamp").className = "lamp on-fault";
    $("#line-updated").textContent = `no data: ${err.message}`;
  }
}

document.addEventListener("DOMContentLoaded", () => {
  $("#shift").addEventListener("change", (ev) => { shiftChoice = ev.target.value; refresh(); });
  header();
  refresh();
  setInterval(refresh, REFRESH_MS);
});
