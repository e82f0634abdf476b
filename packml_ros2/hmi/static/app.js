// PackML HMI: plain JavaScript, no framework, nothing loaded from elsewhere.
// State arrives on one server-sent-events stream (/api/events): a snapshot, then one update per
// change of a unit's status, admin, alarms, transitions or the coordinator's cell status. Actions
// are POSTs to /api/units/<unit>/<action> and /api/cell/<action>; the unit's answer is shown.
"use strict";

(() => {
  // -- constants ---------------------------------------------------------------------------------
  const GROUP = {
    EXECUTE: "g-run",
    IDLE: "g-ready", STARTING: "g-ready", RESETTING: "g-ready", COMPLETING: "g-ready", COMPLETE: "g-ready",
    HOLDING: "g-pause", HELD: "g-pause", UNHOLDING: "g-pause",
    SUSPENDING: "g-pause", SUSPENDED: "g-pause", UNSUSPENDING: "g-pause",
    STOPPING: "g-stop", STOPPED: "g-stop", CLEARING: "g-stop",
    ABORTING: "g-fault", ABORTED: "g-fault",
  };
  const COMMANDS = ["RESET", "START", "STOP", "HOLD", "UNHOLD", "SUSPEND", "UNSUSPEND", "COMPLETE", "CLEAR", "ABORT"];
  const CMD_CLASS = {
    RESET: "c-ready", START: "c-go", STOP: "c-stop", HOLD: "c-pause", UNHOLD: "c-ready",
    SUSPEND: "c-pause", UNSUSPEND: "c-ready", COMPLETE: "c-ready", CLEAR: "c-ready", ABORT: "c-abort",
  };
  const OPERATOR_STATE = ["Active · unacknowledged", "Inactive · unacknowledged", "Acknowledged"];
  const TOKEN_KEY = "packml-hmi-token";

  // The standard PackML state model drawing: 5 columns x 5 rows, Execute in the middle, the Hold
  // loop above it, the Suspend loop below, the reset path on the left, Stop and Abort at the bottom.
  const CX = [86, 266, 446, 626, 806];
  const RY = [52, 132, 212, 322, 424];
  const HW = 58, HH = 21;
  const POS = {
    UNHOLDING: [1, 0], HELD: [2, 0], HOLDING: [3, 0],
    IDLE: [0, 1], STARTING: [1, 1], EXECUTE: [2, 1], COMPLETING: [3, 1], COMPLETE: [4, 1],
    RESETTING: [0, 2], UNSUSPENDING: [1, 2], SUSPENDED: [2, 2], SUSPENDING: [3, 2],
    STOPPED: [0, 3], STOPPING: [1, 3],
    CLEARING: [0, 4], ABORTED: [1, 4], ABORTING: [2, 4],
  };
  const cx = (s) => CX[POS[s][0]], cy = (s) => RY[POS[s][1]];
  const L = (s) => [cx(s) - HW, cy(s)], R = (s) => [cx(s) + HW, cy(s)];
  const T = (s, dx = 0) => [cx(s) + dx, cy(s) - HH], B = (s, dx = 0) => [cx(s) + dx, cy(s) + HH];
  const mid = (a, b, dy = -7) => [(a[0] + b[0]) / 2, a[1] + dy, "middle"];
  const ROUTE_Y = 250, STOP_BOTTOM = 266, ABORT_Y = 372;
  // from, to, command (null = state complete), points, label [x, y, anchor]
  const EDGES = [
    ["STOPPED", "RESETTING", "RESET", [T("STOPPED", -32), B("RESETTING", -32)], [cx("STOPPED") - 26, 292, "start"]],
    ["RESETTING", "IDLE", null, [T("RESETTING"), B("IDLE")]],
    ["IDLE", "STARTING", "START", [R("IDLE"), L("STARTING")], mid(R("IDLE"), L("STARTING"))],
    ["STARTING", "EXECUTE", null, [R("STARTING"), L("EXECUTE")]],
    ["EXECUTE", "COMPLETING", "COMPLETE", [R("EXECUTE"), L("COMPLETING")], mid(R("EXECUTE"), L("COMPLETING"))],
    ["COMPLETING", "COMPLETE", null, [R("COMPLETING"), L("COMPLETE")]],
    ["COMPLETE", "RESETTING", "RESET", [B("COMPLETE"), [cx("COMPLETE"), ROUTE_Y], [cx("RESETTING") + 30, ROUTE_Y], B("RESETTING", 30)], [446, ROUTE_Y - 6, "middle"]],
    ["EXECUTE", "HOLDING", "HOLD", [T("EXECUTE", 32), B("HOLDING", -30)], [cx("EXECUTE") + 104, 104, "start"]],
    ["HOLDING", "HELD", null, [L("HOLDING"), R("HELD")]],
    ["HELD", "UNHOLDING", "UNHOLD", [L("HELD"), R("UNHOLDING")], mid(L("HELD"), R("UNHOLDING"))],
    ["UNHOLDING", "EXECUTE", null, [B("UNHOLDING", 30), T("EXECUTE", -32)]],
    ["EXECUTE", "SUSPENDING", "SUSPEND", [B("EXECUTE", 32), T("SUSPENDING", -30)], [cx("EXECUTE") + 108, 166, "start"]],
    ["SUSPENDING", "SUSPENDED", null, [L("SUSPENDING"), R("SUSPENDED")]],
    ["SUSPENDED", "UNSUSPENDING", "UNSUSPEND", [L("SUSPENDED"), R("UNSUSPENDING")], mid(L("SUSPENDED"), R("UNSUSPENDING"))],
    ["UNSUSPENDING", "EXECUTE", null, [T("UNSUSPENDING", 30), B("EXECUTE", -32)]],
    ["*stop", "STOPPING", "STOP", [[cx("STOPPING"), STOP_BOTTOM], T("STOPPING")], [cx("STOPPING") + 8, 289, "start"]],
    ["STOPPING", "STOPPED", null, [L("STOPPING"), R("STOPPED")]],
    ["*abort", "ABORTING", "ABORT", [[cx("ABORTING"), ABORT_Y], T("ABORTING")], [cx("ABORTING") + 8, 392, "start"]],
    ["ABORTING", "ABORTED", null, [L("ABORTING"), R("ABORTED")]],
    ["ABORTED", "CLEARING", "CLEAR", [L("ABORTED"), R("CLEARING")], mid(L("ABORTED"), R("CLEARING"))],
    ["CLEARING", "STOPPED", null, [T("CLEARING"), B("STOPPED")]],
  ];

  // -- state -------------------------------------------------------------------------------------
  const hmi = (window.__hmi = { renders: [], updates: 0, connected: false, feedback: {} });
  let CFG = null;
  const ST = { units: {}, cell: null };
  let route = { screen: "overview", unit: null };
  let token = sessionStorage.getItem(TOKEN_KEY) || "";
  let tokenOk = false;
  let accessError = "";
  let builtUnit = null;
  const pending = new Set();
  const historyOpen = new Set(); // alarm history sections the operator opened (kept across redraws)

  // -- helpers -----------------------------------------------------------------------------------
  const $ = (sel, root = document) => root.querySelector(sel);
  // Replace an element's content only when it changed: buttons under the operator's finger are
  // not swapped for equal copies by the updates that keep arriving (a click would get lost).
  function setHTML(el, html) {
    if (el && el.__html !== html) {
      el.innerHTML = html;
      el.__html = html;
    }
  }
  const view = (el) => ({ set html(h) { setHTML(el, h); } });
  const $$ = (sel, root = document) => Array.from(root.querySelectorAll(sel));
  const ESC = { "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" };
  const esc = (s) => String(s ?? "").replace(/[&<>"']/g, (c) => ESC[c]);
  const now = () => performance.timeOrigin + performance.now();
  const group = (name) => GROUP[name] || "g-none";
  const canOperate = () => !!CFG && (!CFG.token_required || tokenOk);
  const unitCfg = (name) => CFG.units.find((u) => u.name === name);
  const modeName = (unit, number) => {
    const m = unitCfg(unit)?.modes.find((x) => x.number === number);
    return m ? m.name : `MODE ${number}`;
  };
  const pct = (x) => (Number.isFinite(x) ? `${(x * 100).toFixed(1)} %` : "–");
  // a number the server could not write (NaN, Infinity: JSON null) shows as a dash
  const fixed = (x, digits) => (Number.isFinite(x) ? x.toFixed(digits) : "–");

  function fmtDur(s) {
    s = Math.max(0, Math.floor(s || 0));
    const d = Math.floor(s / 86400), h = Math.floor((s % 86400) / 3600), m = Math.floor((s % 3600) / 60), sec = s % 60;
    const mm = String(m).padStart(2, "0"), ss = String(sec).padStart(2, "0");
    if (d) return `${d}d ${String(h).padStart(2, "0")}:${mm}:${ss}`;
    return `${h}:${mm}:${ss}`;
  }

  function fmtTime(t) {
    if (!t) return "–";
    const d = new Date(t * 1000);
    const time = d.toLocaleTimeString([], { hour12: false });
    return d.toDateString() === new Date().toDateString() ? time : `${d.toLocaleDateString()} ${time}`;
  }

  function chip(name, number, extra = "") {
    if (!name) return `<span class="state-chip g-none ${extra}">NO STATUS</span>`;
    return `<span class="state-chip ${group(name)} ${extra}">${esc(name)}${number !== undefined ? ` <span class="n">${number}</span>` : ""}</span>`;
  }

  function setChip(el, name, number, acting) {
    el.className = `state-chip ${name ? group(name) : "g-none"}${acting ? " acting" : ""}`;
    el.innerHTML = name ? `${esc(name)} <span class="n">${number}</span>` : "–";
  }

  function button(label, act, { unit = "", args = {}, cls = "", enabled = true, title = "" } = {}) {
    return `<button class="btn ${cls}" data-act="${esc(act)}" data-unit="${esc(unit)}" data-args='${esc(JSON.stringify(args))}' data-label="${esc(label)}" ${enabled ? "" : "disabled"} ${title ? `title="${esc(title)}"` : ""}>${esc(label)}</button>`;
  }

  // -- access ------------------------------------------------------------------------------------
  async function verifyToken(candidate) {
    try {
      const r = await fetch("/api/auth", { method: "POST", headers: { Authorization: `Bearer ${candidate}` } });
      const body = await r.json();
      return { ok: r.ok, message: body.message || "" };
    } catch (err) {
      return { ok: false, message: `no answer from the HMI server (${err})` };
    }
  }

  async function unlock(candidate) {
    const res = await verifyToken(candidate);
    if (res.ok) {
      token = candidate;
      tokenOk = true;
      accessError = "";
      sessionStorage.setItem(TOKEN_KEY, candidate);
    } else {
      tokenOk = false;
      accessError = res.message;
    }
    renderAll();
  }

  function lock() {
    token = "";
    tokenOk = false;
    accessError = "";
    sessionStorage.removeItem(TOKEN_KEY);
    renderAll();
  }

  function renderAccess() {
    const el = $("#access");
    if (!CFG) return;
    if (!CFG.token_required) {
      view(el).html = `<span class="badge rw" title="no access token configured (hmi.token)">Operator access</span>`;
      return;
    }
    if (tokenOk) {
      view(el).html = `<span class="badge rw" id="access-state">Operating</span><button id="lock-btn" type="button">Lock</button>`;
      return;
    }
    view(el).html = `<span class="badge ro" id="access-state" title="commands need the access token">Read-only</span>
      <form id="unlock-form"><input id="token-input" type="password" placeholder="access token" autocomplete="off" aria-label="access token">
      <button type="submit">Unlock</button></form>${accessError ? `<span class="err" id="access-error">${esc(accessError)}</span>` : ""}`;
  }

  // -- actions -----------------------------------------------------------------------------------
  async function act(unit, action, args, label) {
    const url = unit ? `/api/units/${encodeURIComponent(unit)}/${action}` : `/api/cell/${action}`;
    const headers = { "Content-Type": "application/json" };
    if (token) headers.Authorization = `Bearer ${token}`;
    const scope = unit || "cell";
    const key = `${scope}/${action}/${JSON.stringify(args)}`;
    pending.add(key);
    let answer;
    try {
      const r = await fetch(url, { method: "POST", headers, body: JSON.stringify(args || {}) });
      answer = await r.json();
      if (r.status === 403 && CFG.token_required) {
        tokenOk = false;
        accessError = answer.message || "access refused";
      }
    } catch (err) {
      answer = { accepted: false, result_name: "NO_CONNECTION", message: `the HMI server did not answer (${err})` };
    } finally {
      pending.delete(key);
    }
    hmi.feedback[scope] = { label, answer, at: Date.now() };
    hmi.lastAnswer = { unit, action, args, answer };
    toast(label, answer, unit);
    renderAll();
    return answer;
  }

  let toastTimer = null;
  function toast(label, answer, unit) {
    const el = $("#toast");
    el.className = `toast ${answer.accepted ? "accepted" : "refused"}`;
    el.textContent = `${unit || "cell"} · ${answer.accepted ? "" : `refused (${answer.result_name || answer.result}): `}${feedbackText(label, answer)}`;
    el.hidden = false;
    clearTimeout(toastTimer);
    toastTimer = setTimeout(() => (el.hidden = true), answer.accepted ? 2500 : 6000);
  }

  function feedbackText(label, answer) {
    if (answer.accepted) return answer.message || `${label} accepted`;
    const why = answer.message || "no reason given";
    return why.toUpperCase().startsWith(label.toUpperCase()) ? why : `${label}: ${why}`;
  }

  function renderFeedback(el, scope) {
    const f = hmi.feedback[scope];
    if (!el) return;
    el.classList.remove("accepted", "refused");
    if (!f) {
      el.textContent = "The unit's answer to your last action appears here.";
      return;
    }
    el.classList.add(f.answer.accepted ? "accepted" : "refused");
    el.innerHTML = `<span class="code">${esc(f.answer.accepted ? "ACCEPTED" : f.answer.result_name || "REFUSED")}</span>${esc(feedbackText(f.label, f.answer))}`;
  }

  document.addEventListener("click", (e) => {
    const go = e.target.closest("[data-go]");
    if (go && !e.target.closest("button")) {
      location.hash = go.dataset.go;
      return;
    }
    const b = e.target.closest("button[data-act]");
    if (b && !b.disabled) {
      act(b.dataset.unit || null, b.dataset.act, JSON.parse(b.dataset.args || "{}"), b.dataset.label);
      return;
    }
    if (e.target.id === "lock-btn") lock();
  });
  document.addEventListener("toggle", (e) => {
    const unit = e.target.dataset?.history;
    if (unit !== undefined) e.target.open ? historyOpen.add(unit) : historyOpen.delete(unit);
  }, true);
  document.addEventListener("submit", (e) => {
    e.preventDefault();
    if (e.target.id === "unlock-form") unlock($("#token-input").value.trim());
    if (e.target.id === "speed-form") {
      const v = parseFloat($("#speed-input").value);
      act(route.unit, "set_mach_speed", { mach_speed: v }, `Speed ${v}`);
    }
  });

  // -- navigation & banner -----------------------------------------------------------------------
  function parseRoute() {
    const parts = location.hash.replace(/^#\/?/, "").split("/").filter(Boolean);
    if (parts[0] === "unit" && parts[1] && CFG && unitCfg(decodeURIComponent(parts[1]))) {
      return { screen: "unit", unit: decodeURIComponent(parts[1]) };
    }
    if (parts[0] === "alarms") return { screen: "alarms", unit: parts[1] ? decodeURIComponent(parts[1]) : null };
    return { screen: "overview", unit: null };
  }

  function alarmCount(name) {
    const s = ST.units[name]?.status;
    return s ? s.unacknowledged_alarms || s.active_alarms : 0;
  }

  function renderNav() {
    const nav = $("#nav");
    const totalAlarms = CFG.units.reduce((n, u) => n + ((ST.units[u.name]?.alarms?.alarms || []).length), 0);
    const unack = CFG.units.reduce((n, u) => n + (ST.units[u.name]?.status?.unacknowledged_alarms || 0), 0);
    const tabs = [`<a href="#/overview" data-screen="overview" class="${route.screen === "overview" ? "active" : ""}">Overview</a>`];
    for (const u of CFG.units) {
      const s = ST.units[u.name]?.status;
      const active = route.screen === "unit" && route.unit === u.name;
      tabs.push(`<a href="#/unit/${encodeURIComponent(u.name)}" data-screen="unit" data-unit="${esc(u.name)}" class="${active ? "active" : ""}"><span class="dot ${s ? group(s.state_name) : ""}"></span>${esc(u.name)}${alarmCount(u.name) ? ` <span class="count hot">${alarmCount(u.name)}</span>` : ""}</a>`);
    }
    tabs.push(`<a href="#/alarms" data-screen="alarms" class="${route.screen === "alarms" ? "active" : ""}">Alarms <span class="count ${unack ? "hot" : ""}" id="nav-alarm-count">${totalAlarms}</span></a>`);
    view(nav).html = tabs.join("");
  }

  function cellMode() {
    const modes = new Set(CFG.units.map((u) => ST.units[u.name]?.status?.mode_name).filter(Boolean));
    if (modes.size === 1) {
      const name = [...modes][0];
      const s = Object.values(ST.units).find((u) => u.status)?.status;
      return `${name} (${s.mode})`;
    }
    return modes.size ? "MIXED" : "–";
  }

  function renderBanner() {
    const unit = route.screen === "unit" ? route.unit : route.screen === "alarms" ? route.unit : null;
    const modeEl = $("#banner-mode"), stateEl = $("#banner-state"), alarmEl = $("#banner-alarm");
    let alarm = "", unack = false;
    if (unit) {
      const s = ST.units[unit]?.status;
      $("#banner-scope").textContent = unit;
      modeEl.textContent = s ? `${s.mode_name} (${s.mode})` : "–";
      setChip(stateEl, s?.state_name, s?.state, s?.acting);
      alarm = s?.alarm_banner || "";
      unack = !!s?.unacknowledged_alarms;
    } else {
      $("#banner-scope").textContent = `Cell ${CFG.title}`;
      modeEl.textContent = cellMode();
      const c = ST.cell;
      if (c) setChip(stateEl, c.state_name, c.state, false);
      else {
        const first = Object.values(ST.units).find((u) => u.status)?.status;
        setChip(stateEl, first?.state_name, first?.state, first?.acting);
      }
      for (const u of CFG.units) {
        const s = ST.units[u.name]?.status;
        if (s?.alarm_banner) {
          alarm = `${u.name}: ${s.alarm_banner}`;
          unack = !!s.unacknowledged_alarms;
          break;
        }
      }
    }
    alarmEl.className = `banner-alarm ${alarm ? "active" : "ok"}${unack ? " unack" : ""}`;
    view(alarmEl).html = alarm
      ? `<span class="lamp"></span><span id="banner-alarm-text">${esc(alarm)}</span>`
      : `<span class="lamp on-ok"></span><span id="banner-alarm-text">No active alarm</span>`;
  }

  // -- overview ----------------------------------------------------------------------------------
  function renderOverview() {
    const el = $("#screen-overview");
    const c = ST.cell;
    const online = CFG.units.filter((u) => ST.units[u.name]?.online).length;
    const valid = new Set(CFG.units.flatMap((u) => ST.units[u.name]?.status?.commands_valid_names || []));
    const cellCmds = CFG.coordinator
      ? COMMANDS.map((name) => {
          const ok = valid.has(name) && canOperate() && !!c && (!c.busy || name === "STOP" || name === "ABORT");
          return button(name, "command", { args: { command: name }, cls: `cmd ${valid.has(name) ? `valid ${CMD_CLASS[name]}` : ""}`, enabled: ok });
        }).join("")
      : `<span class="muted">no coordinator configured</span>`;
    const cellCard = `<div class="card"><div class="cell-card">
      <div><div class="muted">Cell</div><div class="cell-name">${esc(CFG.title)}</div></div>
      <div>
        <div class="row">${c ? chip(c.state_name, c.state, "big") : chip(null)}
          ${c?.busy ? `<span class="tag info">sequence running: ${esc(c.sequence_step || "…")}</span>` : ""}
          ${c && c.lost_units.length ? `<span class="tag bad">lost: ${esc(c.lost_units.join(", "))}</span>` : ""}</div>
        <div class="cell-meta mt-s">
          <span>Mode <b>${esc(cellMode())}</b></span>
          <span>Units online <b>${online}/${CFG.units.length}</b></span>
          <span>Coordinator <b>${CFG.coordinator ? (c ? "running" : "no status") : "none"}</b></span>
          ${c?.detail ? `<span>${esc(c.detail)}</span>` : ""}
        </div>
      </div>
      <div><div class="muted cell-cmds-title">Cell commands (through the coordinator, in the configured order)</div><div class="cell-cmds" id="cell-cmds">${cellCmds}</div></div>
      <div class="feedback span-all" id="cell-feedback"></div>
    </div></div>`;
    const cards = CFG.units.map((u) => unitCard(u)).join("");
    if (!$("#ov-cell")) el.innerHTML = `<div id="ov-cell"></div><div class="grid units mt" id="unit-cards"></div>`;
    setHTML($("#ov-cell"), cellCard);
    setHTML($("#unit-cards"), cards);
    renderFeedback($("#cell-feedback"), "cell");
    for (const u of CFG.units) {
      const bar = $(`#oee-${u.name} > i`);
      const a = ST.units[u.name]?.admin;
      if (bar) bar.style.width = `${Math.min(100, (a?.oee.oee || 0) * 100)}%`;
    }
  }

  function unitCard(u) {
    const x = ST.units[u.name] || {};
    const s = x.status, a = x.admin;
    const summary = ST.cell?.units.find((v) => v.name === u.name);
    const health = !x.online ? "offline" : summary?.health || (s?.active_alarms ? "alarm" : "ok");
    const healthCls = health === "ok" ? "ok" : health === "alarm" ? "bad" : "warn";
    const ems = s?.equipment_modules || [];
    const sum = (list) => (list || []).reduce((n, c) => n + c.count, 0);
    const processed = sum(a?.counters.processed), defective = sum(a?.counters.defective);
    const emDots = ems.map((e) => `<span class="em-dot"><span class="lamp ${!e.active ? "" : e.online ? "on-ok" : "on-fault"}"></span>${esc(e.name)}</span>`).join("");
    return `<div class="card unit-card" data-go="#/unit/${encodeURIComponent(u.name)}" data-unit-card="${esc(u.name)}">
      <div class="head"><div><div class="name">${esc(u.name)}</div><div class="desc">${esc(u.description)}</div></div>
        ${chip(s?.state_name, s?.state, `big${s?.acting ? " acting" : ""}`)}</div>
      <div class="facts">
        <div class="fact"><div class="k">Mode</div><div class="v">${esc(s?.mode_name || "–")}</div></div>
        <div class="fact"><div class="k">Health</div><div class="v"><span class="tag ${healthCls}">${esc(health)}</span></div></div>
        <div class="fact"><div class="k">EMs online</div><div class="v">${ems.filter((e) => e.online).length}/${ems.length}</div></div>
        <div class="fact"><div class="k">Speed</div><div class="v">${s ? `${fixed(s.cur_mach_speed, 0)}/${fixed(s.mach_speed, 0)}` : "–"}</div></div>
        <div class="fact"><div class="k">Processed</div><div class="v">${processed}</div></div>
        <div class="fact"><div class="k">Defective</div><div class="v">${defective}</div></div>
        <div class="fact"><div class="k">Alarms</div><div class="v">${s?.active_alarms ?? 0}</div></div>
        <div class="fact"><div class="k">OEE</div><div class="v">${a ? pct(a.oee.oee) : "–"}</div></div>
      </div>
      <div class="bar" id="oee-${esc(u.name)}"><i></i></div>
      <div class="em-dots">${emDots || `<span class="muted">no equipment modules</span>`}</div>
      <div class="alarm-line ${s?.alarm_banner ? "active" : ""}">${esc(s?.alarm_banner || "No active alarm")}</div>
    </div>`;
  }

  // -- unit screen -------------------------------------------------------------------------------
  const NS = "http://www.w3.org/2000/svg";
  function svg(tag, attrs = {}, parent = null, text = null) {
    const e = document.createElementNS(NS, tag);
    for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
    if (text !== null) e.textContent = text;
    if (parent) parent.appendChild(e);
    return e;
  }

  function buildDiagram() {
    const root = svg("svg", { viewBox: "0 0 896 466", id: "diagram", role: "img", "aria-label": "PackML state model" });
    const defs = svg("defs", {}, root);
    for (const [id, color] of [["arr", "#9aa7b4"], ["arr-on", "#1f6feb"]]) {
      const m = svg("marker", { id, viewBox: "0 0 10 10", refX: "9", refY: "5", markerWidth: "7", markerHeight: "7", orient: "auto-start-reverse" }, defs);
      svg("path", { d: "M0,0 L10,5 L0,10 z", fill: color }, m);
    }
    const hatch = svg("pattern", { id: "hatch", width: "7", height: "7", patternUnits: "userSpaceOnUse", patternTransform: "rotate(45)" }, defs);
    svg("rect", { width: "7", height: "7", fill: "#f1f3f5" }, hatch);
    svg("line", { x1: "0", y1: "0", x2: "0", y2: "7", stroke: "#dde2e7", "stroke-width": "3" }, hatch);

    // regions: Abort is valid everywhere except Aborting/Aborted, Stop everywhere above Stopping
    svg("path", { class: "region", d: `M4,8 H892 V${ABORT_Y} H176 V458 H4 Z` }, root);
    svg("rect", { class: "region", x: "12", y: "16", width: "872", height: STOP_BOTTOM - 16, rx: "8" }, root);
    svg("text", { class: "region-label", x: "876", y: "34", "text-anchor": "end" }, root, "Stop: from every state in this box");
    svg("text", { class: "region-label", x: "884", y: "364", "text-anchor": "end" }, root, "Abort: from every state in this box");

    for (const [from, to, cmd, pts, label] of EDGES) {
      const d = pts.map((p, i) => `${i ? "L" : "M"}${p[0]},${p[1]}`).join(" ");
      svg("path", { class: "edge", d, "marker-end": "url(#arr)", "data-from": from, "data-to": to, "data-cmd": cmd || "" }, root);
      if (label && cmd) {
        svg("text", { class: "edge-label", x: label[0], y: label[1], "text-anchor": label[2], "data-from": from, "data-cmd": cmd }, root, cmd[0] + cmd.slice(1).toLowerCase());
      }
    }
    for (const st of CFG.states) {
      const [c, r] = POS[st.name];
      const x = CX[c], y = RY[r];
      const g = svg("g", { class: `st ${st.acting ? "acting" : "wait"}`, "data-state": st.name, "data-number": st.number, id: `st-${st.name}` }, root);
      const rx = st.acting ? HH : 3;
      svg("rect", { class: "pulse", x: x - HW, y: y - HH, width: 2 * HW, height: 2 * HH, rx }, g);
      svg("rect", { x: x - HW, y: y - HH, width: 2 * HW, height: 2 * HH, rx }, g);
      svg("text", { x, y: y + 2 }, g, st.name);
      svg("text", { class: "nr", x, y: y + 15 }, g, String(st.number));
      svg("title", {}, g, `${st.number} ${st.name} (${st.acting ? "acting state: left by state complete or a command" : "wait state: left by a command"})`);
    }
    // legend (bottom right)
    const lg = svg("g", { class: "legend" }, root);
    const item = (x, y, draw, text) => {
      draw(x, y);
      svg("text", { x: x + 32, y: y + 10 }, lg, text);
    };
    item(540, 398, (x, y) => svg("rect", { x, y, width: 24, height: 13, rx: 3, fill: "#1565c0", stroke: "#0b1520" }, lg), "current state");
    item(716, 398, (x, y) => svg("rect", { x, y, width: 24, height: 13, rx: 3, fill: "#fff", stroke: "#1f6feb", "stroke-dasharray": "4 3" }, lg), "target wait state");
    item(540, 420, (x, y) => svg("rect", { x, y, width: 24, height: 13, rx: 6.5, fill: "#fff", stroke: "#0b1520", "stroke-dasharray": "5 3" }, lg), "acting, in progress");
    item(716, 420, (x, y) => svg("rect", { x, y, width: 24, height: 13, rx: 3, fill: "url(#hatch)", stroke: "#c9d1d9" }, lg), "disabled in this mode");
    item(540, 442, (x, y) => svg("path", { d: `M${x},${y + 6} H${x + 22}`, stroke: "#1f6feb", "stroke-width": 2.4, "marker-end": "url(#arr-on)" }, lg), "command valid now");
    item(716, 442, (x, y) => svg("path", { d: `M${x},${y + 6} H${x + 22}`, stroke: "#9aa7b4", "stroke-width": 1.6, "marker-end": "url(#arr)" }, lg), "unlabelled: state complete");
    return root;
  }

  function buildUnit(name) {
    const el = $("#screen-unit");
    const u = unitCfg(name);
    el.innerHTML = `
      <div class="grid cols-unit">
        <div class="stack">
          <div class="card diagram"><h2>State model <span class="sub" id="u-model-sub"></span><span class="right muted" id="u-seq"></span></h2>
            <div id="u-diagram"></div><div class="progress-line" id="u-progress"></div></div>
          <div class="card"><h2>Commands <span class="sub">only the commands valid now are enabled</span></h2>
            <div class="cmds" id="u-cmds">${COMMANDS.map((c) => `<button class="btn cmd" data-act="command" data-unit="${esc(name)}" data-cmd="${c}" data-label="${c}" data-args='${esc(JSON.stringify({ command: c }))}' disabled>${c}</button>`).join("")}</div>
            <div class="feedback" id="u-feedback"></div><div class="readonly-note" id="u-ro"></div></div>
        </div>
        <div class="stack">
          <div class="card"><h2>Unit mode <span class="right" id="u-mode-now"></span></h2>
            <div class="modes" id="u-modes">${u.modes.map((m) => `<button class="btn mode-btn" data-act="set_mode" data-unit="${esc(name)}" data-mode="${m.number}" data-label="Mode ${esc(m.name)}" data-args='${esc(JSON.stringify({ mode: m.number }))}' title="mode ${m.number}; mode change allowed in ${esc(m.change_allowed.join(", "))}">${esc(m.name)}</button>`).join("")}</div>
            <div class="lamps" id="u-lamps"></div>
            <form class="speed" id="speed-form"><span class="muted">Machine speed</span><input id="speed-input" type="number" step="any" min="0" aria-label="machine speed setpoint"><button class="btn small" id="speed-btn" type="submit">Set</button><span class="muted" id="u-speed"></span></form>
          </div>
          <div class="card"><h2>Equipment modules <span class="sub" id="u-em-sub"></span></h2>
            <table id="u-ems"><thead><tr><th>EM</th><th>Active</th><th>Online</th><th>State complete</th><th>Request / interlock</th><th></th></tr></thead><tbody></tbody></table>
            <div class="readonly-note">Switching an EM active/inactive is allowed outside Production only, and logged.</div></div>
          <div class="card"><h2>Alarms <a class="right" href="#/alarms/${encodeURIComponent(name)}">alarm list →</a></h2><div id="u-alarms"></div></div>
        </div>
      </div>
      <div class="grid cols-3 mt">
        <div class="card"><h2>Times <span class="sub" id="u-times-mode"></span></h2><div id="u-times"></div>
          <div class="row mt-s" id="u-time-keys"></div></div>
        <div class="stack">
          <div class="card"><h2>Counters</h2><div id="u-counters"></div><div class="row mt-s" id="u-counter-keys"></div></div>
          <div class="card"><h2>Stop reason</h2><div id="u-stop"></div></div>
        </div>
        <div class="stack">
          <div class="card"><h2>OEE <span class="sub">Production mode</span></h2><div id="u-oee"></div></div>
          <div class="card"><h2>Recent transitions</h2><div id="u-transitions"></div></div>
        </div>
      </div>`;
    $("#u-diagram").appendChild(buildDiagram());
    builtUnit = name;
  }

  function renderUnit(parts = null) {
    const name = route.unit;
    if (builtUnit !== name || !$("#diagram")) {
      buildUnit(name);
      parts = null;
    }
    const x = ST.units[name] || {};
    const all = !parts;
    if (all || parts.has("status")) renderUnitStatus(name, x);
    if (all || parts.has("status") || parts.has("admin")) renderUnitAdmin(name, x);
    if (all || parts.has("alarms") || parts.has("status")) renderUnitAlarms(name, x);
    if (all || parts.has("transition")) renderTransitions(x);
    renderFeedback($("#u-feedback"), name);
  }

  function renderUnitStatus(name, x) {
    const s = x.status;
    const valid = new Set(s?.commands_valid_names || []);
    const operate = canOperate() && !!s && x.online;
    // diagram
    for (const g of $$("#diagram .st")) {
      const n = +g.dataset.number, st = g.dataset.state;
      let cls = `st ${g.classList.contains("acting") ? "acting" : "wait"}`;
      if (s) {
        if (s.states_disabled & (1 << n)) cls += " disabled";
        if (n === s.state) cls += ` current ${group(st)}`;
        else if (s.state_change_in_process && n === s.state_requested) cls += " target";
      }
      g.setAttribute("class", cls);
    }
    for (const p of $$("#diagram .edge, #diagram .edge-label")) {
      const from = p.dataset.from, cmd = p.dataset.cmd;
      let on = false;
      if (s) {
        if (cmd) on = valid.has(cmd) && (from === s.state_name || (from === "*stop" && cmd === "STOP") || (from === "*abort" && cmd === "ABORT"));
        else on = from === s.state_name && s.acting;
      }
      p.classList.toggle("possible", on);
      if (p.tagName === "path") p.setAttribute("marker-end", on ? "url(#arr-on)" : "url(#arr)");
    }
    $("#u-model-sub").textContent = s ? `${s.mode_name} mode · ${countBits(s.states_disabled)} state(s) disabled` : "";
    $("#u-seq").textContent = s ? `transition #${s.sequence}` : "";
    const prog = $("#u-progress");
    if (!s) prog.textContent = x.online ? "" : "No status from this unit (is it running?)";
    else if (s.state_name === "EXECUTE") {
      view(prog).html = `<b>EXECUTE</b>: producing · leaves by a command, or to COMPLETING when the run is finished (state complete)`;
    } else if (s.acting) {
      const waiting = s.equipment_modules.filter((e) => e.active && !e.state_complete).map((e) => e.name);
      view(prog).html = `<b>${esc(s.state_name)}</b> in progress → ${esc(s.state_requested_name)}${waiting.length ? ` · waiting for state complete from ${esc(waiting.join(", "))}` : ""}`;
    } else view(prog).html = `<b>${esc(s.state_name)}</b>: waiting for a command (valid now: ${esc([...valid].join(", ") || "none")})`;

    // commands
    for (const b of $$("#u-cmds button")) {
      const c = b.dataset.cmd;
      b.className = `btn cmd${valid.has(c) ? ` valid ${CMD_CLASS[c]}` : ""}`;
      b.disabled = !(operate && valid.has(c));
    }
    $("#u-ro").textContent = !canOperate() ? "Read-only: enter the access token (top right) to operate." : !x.online ? "The unit is not answering." : "";

    // mode
    for (const b of $$("#u-modes button")) {
      const m = +b.dataset.mode;
      b.classList.toggle("current", !!s && m === s.mode);
      b.classList.toggle("requested", !!s && s.mode_change_in_process && m === s.mode_requested);
      b.disabled = !operate || (!!s && m === s.mode);
    }
    view($("#u-mode-now")).html = s ? `<b>${esc(s.mode_name)}</b> <span class="muted">(${s.mode})</span>` : "";
    const lamp = (on, cls, text, id) => `<div class="lamp-row ${on ? "lit" : ""}" id="${id}" data-on="${on}"><span class="lamp ${on ? cls : ""}"></span>${esc(text)}</div>`;
    view($("#u-lamps")).html = s
      ? lamp(s.mode_change_not_allowed, "on-fault blink", "Mode change not allowed", "lamp-mode-refused") +
        lamp(s.mode_change_in_process, "on-info", s.mode_change_in_process ? `Mode change in process → ${modeName(name, s.mode_requested)}` : "Mode change in process", "lamp-mode-change") +
        lamp(s.remote_commands_enabled, "on-ok", "Remote commands enabled (coordinator)", "lamp-remote") +
        lamp(s.blocked || s.starved, "on-warn", s.blocked ? "Blocked (downstream)" : s.starved ? "Starved (upstream)" : "Blocked / starved", "lamp-interlock")
      : "";
    const speedInput = $("#speed-input");
    if (document.activeElement !== speedInput && s) speedInput.value = s.mach_speed ?? "";
    speedInput.disabled = !operate;
    $("#speed-btn").disabled = !operate;
    $("#u-speed").textContent = s ? `actual ${fixed(s.cur_mach_speed, 1)}${unitCfg(name).mach_design_speed ? ` · design ${unitCfg(name).mach_design_speed}` : ""}` : "";

    // EMs
    const inProduction = s?.mode === 1;
    $("#u-em-sub").textContent = s ? `state complete for ${s.state_name}` : "";
    const rows = (s?.equipment_modules || []).map((e) => {
      const sc = !s.acting ? `<span class="muted">–</span>` : e.active ? (e.state_complete ? `<span class="lamp on-ok"></span> done` : `<span class="lamp on-warn blink"></span> running`) : `<span class="muted">ignored</span>`;
      const flags = [e.blocked ? `<span class="tag warn">blocked</span>` : "", e.starved ? `<span class="tag warn">starved</span>` : ""].join(" ");
      const label = e.active ? "Switch off" : "Switch on";
      return `<tr data-em="${esc(e.name)}"><td><b>${esc(e.name)}</b>${e.configured ? "" : ` <span class="tag info">registered</span>`}</td>
        <td>${e.active ? `<span class="tag ok">active</span>` : `<span class="tag">inactive</span>`}</td>
        <td><span class="lamp ${e.online ? "on-ok" : e.active ? "on-fault" : ""}"></span> ${e.online ? "online" : "offline"}</td>
        <td>${sc}</td><td>${e.command_request_name ? `<span class="tag bad">${esc(e.command_request_name)}</span> ` : ""}${flags.trim() || (e.command_request_name ? "" : `<span class="muted">–</span>`)}</td>
        <td>${button(label, "set_em_active", { unit: name, args: { em: e.name, active: !e.active }, cls: "small", enabled: operate && !inProduction, title: inProduction ? "only outside Production" : "" })}</td></tr>`;
    });
    view($("#u-ems tbody")).html = rows.join("") || `<tr><td colspan="6" class="empty">no equipment modules</td></tr>`;
  }

  function countBits(n) {
    let c = 0;
    for (; n; n &= n - 1) c++;
    return c;
  }

  function renderUnitAdmin(name, x) {
    const s = x.status, a = x.admin;
    const operate = canOperate() && x.online;
    const mode = s?.mode ?? 1;
    const t = a?.times?.[String(mode)];
    $("#u-times-mode").textContent = s ? `${s.mode_name} mode` : "";
    if (!t) view($("#u-times")).html = `<div class="empty">no admin data yet</div>`;
    else {
      const rows = CFG.states.map((st) => {
        const cls = s && st.number === s.state ? "current-row" : s && s.states_disabled & (1 << st.number) ? "disabled-row" : "";
        return `<tr class="${cls}"><td>${esc(st.name)}</td><td class="num">${fmtDur(t.state_current[st.number])}</td><td class="num">${fmtDur(t.state_cumulative[st.number])}</td></tr>`;
      });
      view($("#u-times")).html = `<dl class="kv"><dt>In this mode since entry</dt><dd class="num" id="t-mode-current">${fmtDur(t.mode_current)}</dd>
        <dt>In this mode, cumulative</dt><dd class="num">${fmtDur(t.mode_cumulative)}</dd>
        <dt>Since reset of all times</dt><dd class="num">${fmtDur(a.acc_time_since_reset)}</dd></dl>
        <table class="mt-s"><thead><tr><th>State</th><th class="num">Current</th><th class="num">Cumulative</th></tr></thead><tbody>${rows.join("")}</tbody></table>`;
    }
    view($("#u-time-keys")).html =
      button("Reset times of this mode", "reset_times", { unit: name, args: { scope: "mode" }, cls: "small", enabled: operate }) +
      button("Reset all times", "reset_times", { unit: name, args: { scope: "all" }, cls: "small", enabled: operate });

    // counters
    const kinds = [["consumed", "Consumed"], ["processed", "Processed"], ["defective", "Defective"]];
    const crow = [];
    for (const [k, label] of kinds) {
      for (const c of a?.counters[k] || []) {
        if (!c.name && !c.count && !c.acc_count) continue;
        crow.push(`<tr><td>${label}</td><td>${esc(c.name || `#${c.id}`)}</td><td class="num"><b>${c.count}</b></td><td class="num">${c.acc_count}</td><td class="muted">${esc(c.unit)}</td></tr>`);
      }
    }
    view($("#u-counters")).html = crow.length
      ? `<table><thead><tr><th>Kind</th><th>Counter</th><th class="num">Count</th><th class="num">Lifetime</th><th></th></tr></thead><tbody>${crow.join("")}</tbody></table>`
      : `<div class="empty">no counters configured</div>`;
    view($("#u-counter-keys")).html = button("Reset counters", "reset_counters", { unit: name, cls: "small", enabled: operate });

    // stop reason
    const r = a?.stop_reason;
    view($("#u-stop")).html = r
      ? `<dl class="kv"><dt>Event</dt><dd>${esc(r.kind === "command" ? `command ${r.message || ""}` : `${r.kind} ${r.id}/${r.value}: ${r.message}`)}</dd>
         <dt>Source</dt><dd>${esc(r.source || "–")}</dd><dt>When</dt><dd>${fmtTime(r.time)}</dd>
         ${r.reaction_name ? `<dt>Reaction</dt><dd>${esc(r.reaction_name)}</dd>` : ""}</dl>`
      : `<div class="empty">no stop recorded since the last reset</div>`;

    // OEE
    if (!a) view($("#u-oee")).html = `<div class="empty">no admin data yet</div>`;
    else {
      const o = a.oee;
      const bar = (label, v, cls = "") => `<div class="bar-row ${cls}"><span>${label}</span><div class="bar"><i data-w="${Math.min(1, v || 0)}"></i></div><span class="num">${pct(v)}</span></div>`;
      view($("#u-oee")).html = `<div class="bars">${bar("Availability", o.availability)}${bar("Performance", o.performance)}${bar("Quality", o.quality)}${bar("OEE", o.oee, "total")}</div>
        <dl class="kv mt-s"><dt>Production time</dt><dd class="num">${fmtDur(o.production_time)}</dd><dt>Execute time</dt><dd class="num">${fmtDur(o.execute_time)}</dd>
        <dt>Internal downtime (held)</dt><dd class="num">${fmtDur(o.internal_downtime)}</dd><dt>External downtime (suspended)</dt><dd class="num">${fmtDur(o.external_downtime)}</dd>
        <dt>Stopped / aborted</dt><dd class="num">${fmtDur(o.stopped_time)} / ${fmtDur(o.aborted_time)}</dd><dt>Processed / defective</dt><dd class="num">${o.processed} / ${o.defective}</dd></dl>`;
      for (const i of $$("#u-oee .bar > i")) i.style.width = `${+i.dataset.w * 100}%`;
    }
  }

  function renderUnitAlarms(name, x) {
    const s = x.status, list = x.alarms?.alarms || [];
    const rows = list.slice(0, 4).map((al) => `<tr class="al-${al.operator_state}${al.trigger ? " still" : ""}"><td class="first"><span class="lamp ${alarmLamp(al)}"></span></td><td>${al.id}/${al.value}</td><td class="msg">${esc(al.message)}</td><td>${esc(OPERATOR_STATE[al.operator_state] || "")}</td></tr>`);
    view($("#u-alarms")).html = `<div class="row"><span>Active <b>${s?.active_alarms ?? 0}</b></span><span>Unacknowledged <b>${s?.unacknowledged_alarms ?? 0}</b></span>
      ${x.alarms?.first_out ? `<span class="muted">first out: ${esc(`${x.alarms.first_out.id}/${x.alarms.first_out.value} ${x.alarms.first_out.message}`)}</span>` : ""}</div>
      ${rows.length ? `<table class="alarm-table mt-s"><tbody>${rows.join("")}</tbody></table>` : `<div class="empty">no alarms</div>`}
      ${list.length > 4 ? `<div class="muted">… ${list.length - 4} more in the alarm list</div>` : ""}`;
  }

  const TRIGGER = { STATE_COMPLETE: "state complete", COMMAND: "command", ALARM: "alarm", INTERLOCK: "interlock", SKIP: "skipped (disabled)", MODE: "mode change", EM_LOST: "EM lost", TIMEOUT: "timeout", RESTART: "unit (re)started" };

  function renderTransitions(x) {
    const list = (x.transitions || []).slice(-8).reverse();
    view($("#u-transitions")).html = list.length
      ? `<table class="transitions"><tbody>${list
          .map((t) => {
            const what = t.from_state === t.to_state ? `mode ${t.from_mode} → ${t.to_mode} in ${esc(t.to_state)}` : `${esc(t.from_state)} → <b>${esc(t.to_state)}</b>`;
            const why = `${t.command || TRIGGER[t.trigger] || t.trigger.toLowerCase()}${t.source ? ` · ${t.source}` : ""}`;
            return `<tr><td class="num muted">#${t.sequence}</td><td class="num">${fmtTime(t.stamp)}</td><td>${what}<div class="muted small">${esc(why)}${t.detail ? ` · ${esc(t.detail)}` : ""}</div></td></tr>`;
          })
          .join("")}</tbody></table>`
      : `<div class="empty">none yet</div>`;
  }

  // -- alarms screen -----------------------------------------------------------------------------
  function alarmLamp(al) {
    if (al.kind === "warning") return al.trigger ? "on-warn" : "";
    if (al.operator_state === 0) return "on-fault blink";
    if (al.operator_state === 1) return "on-warn";
    return al.trigger ? "on-fault" : "";
  }

  function alarmRows(unit, list, operate) {
    return list
      .map((al) => `<tr class="${al.kind === "warning" ? "warning-row" : `al-${al.operator_state}`}${al.trigger ? " still" : ""}" data-alarm="${al.id}/${al.value}" data-operator-state="${al.operator_state}">
        <td class="first"><span class="lamp ${alarmLamp(al)}"></span></td>
        <td>${al.kind === "warning" ? (al.trigger ? "Warning · active" : "Warning · cleared") : esc(OPERATOR_STATE[al.operator_state] || "")}${al.kind !== "warning" && al.operator_state === 2 && al.trigger ? ` <span class="tag bad">still active</span>` : ""}</td>
        <td class="num">${al.id}/${al.value}</td><td class="num">${al.category}</td><td class="msg">${esc(al.message)}</td>
        <td>${esc(al.em || "–")}</td><td class="muted">${esc(al.source)}</td><td>${fmtTime(al.time)}</td><td>${fmtTime(al.ack_time)}</td><td>${fmtTime(al.cleared_time)}</td>
        <td>${al.reaction_name ? `<span class="tag">${esc(al.reaction_name)}</span>` : "–"}</td>
        <td>${al.kind === "alarm" ? button("Ack", "ack_alarms", { unit, args: { all: false, id: al.id, value: al.value }, cls: "small", enabled: operate && !al.acknowledged }) : ""}</td></tr>`)
      .join("");
  }

  function renderAlarms() {
    const el = $("#screen-alarms");
    const units = route.unit && unitCfg(route.unit) ? [unitCfg(route.unit)] : CFG.units;
    const head = `<tr><th></th><th>State</th><th class="num">ID/Value</th><th class="num">Cat</th><th>Message</th><th>EM</th><th>Source</th><th>Raised</th><th>Acknowledged</th><th>Cleared</th><th>Reaction</th><th></th></tr>`;
    const filters = [`<a class="btn small ${route.unit ? "" : "primary"}" href="#/alarms">All units</a>`]
      .concat(CFG.units.map((u) => `<a class="btn small ${route.unit === u.name ? "primary" : ""}" href="#/alarms/${encodeURIComponent(u.name)}">${esc(u.name)}</a>`))
      .join("");
    const sections = units.map((u) => {
      const x = ST.units[u.name] || {};
      const operate = canOperate() && x.online;
      const list = x.alarms?.alarms || [], warnings = x.alarms?.warnings || [];
      const unack = list.filter((a) => !a.acknowledged).length;
      const history = (x.admin?.history || []).slice(0, 15);
      return `<div class="card" data-alarm-unit="${esc(u.name)}"><h2>${esc(u.name)} <span class="sub">${list.length} alarm(s), ${unack} unacknowledged, ${warnings.length} warning(s)</span>
          <span class="right row">${button("Acknowledge all", "ack_alarms", { unit: u.name, args: { all: true }, cls: "small", enabled: operate && unack > 0 })}
          ${button("Reset alarms", "reset_alarms", { unit: u.name, cls: "small", enabled: operate && list.length > 0 })}</span></h2>
        ${list.length ? `<table class="alarm-table"><thead>${head}</thead><tbody>${alarmRows(u.name, list, operate)}</tbody></table>` : `<div class="empty">No alarms</div>`}
        ${warnings.length ? `<h3 class="sub-head">Warnings <span class="muted">(no acknowledgement; they never change the state)</span></h3><table class="alarm-table"><thead>${head}</thead><tbody>${alarmRows(u.name, warnings, operate)}</tbody></table>` : ""}
        <div class="feedback" data-feedback="${esc(u.name)}"></div>
        <details data-history="${esc(u.name)}" ${historyOpen.has(u.name) ? "open" : ""}><summary>History (newest first)</summary>${history.length ? `<table><tbody>${history.map((h) => `<tr><td>${fmtTime(h.time)}</td><td>${esc(h.kind)}</td><td>${h.id}/${h.value}</td><td>${esc(h.message)}</td><td class="muted">${esc(h.source)}</td></tr>`).join("")}</tbody></table>` : `<div class="empty">empty</div>`}</details>
      </div>`;
    });
    view(el).html = `<div class="card"><div class="row"><div class="row">${filters}</div>
        <div class="legend-row"><span><span class="lamp on-fault blink"></span>active, unacknowledged</span><span><span class="lamp on-warn"></span>inactive, unacknowledged</span>
        <span><span class="lamp on-fault"></span>acknowledged, still active</span><span><span class="lamp"></span>acknowledged, cleared (reset removes it)</span></div></div></div>
      <div class="stack mt">${sections.join("")}</div>`;
    for (const f of $$("[data-feedback]", el)) renderFeedback(f, f.dataset.feedback);
  }

  // -- rendering ---------------------------------------------------------------------------------
  function showScreen() {
    for (const s of ["overview", "unit", "alarms"]) $(`#screen-${s}`).hidden = s !== route.screen;
  }

  function renderAll() {
    if (!CFG) return;
    document.title = `${CFG.title} · PackML HMI`;
    $("#title").textContent = `PackML HMI · ${CFG.title}`;
    showScreen();
    renderAccess();
    renderNav();
    renderBanner();
    if (route.screen === "overview") renderOverview();
    else if (route.screen === "unit") renderUnit();
    else renderAlarms();
  }

  function renderUpdate(ev) {
    const topic = ev.topic;
    renderBanner();
    if (topic === "status" || topic === "alarms" || topic === "online") renderNav();
    if (route.screen === "overview") {
      if (topic !== "transition") renderOverview();
    } else if (route.screen === "unit") {
      if (ev.unit === route.unit) renderUnit(new Set([topic === "online" ? "status" : topic]));
    } else if (route.screen === "alarms" && topic !== "transition" && topic !== "cell") {
      if (!route.unit || ev.unit === route.unit) renderAlarms();
    }
  }

  function apply(ev) {
    hmi.updates++;
    if (ev.topic === "cell") ST.cell = ev.data;
    else {
      const u = (ST.units[ev.unit] ||= { status: null, admin: null, alarms: null, transitions: [], online: false });
      if (ev.topic === "transition") {
        u.transitions.push(ev.data);
        if (u.transitions.length > 30) u.transitions.shift();
      } else if (ev.topic === "online") u.online = ev.data;
      else {
        u[ev.topic] = ev.data;
        u.online = true;
      }
    }
    renderUpdate(ev);
    if (ev.topic === "status") {
      const rec = { unit: ev.unit, seq: ev.data.sequence, state: ev.data.state_name, stamp: ev.data.stamp * 1000, received: ev.received, arrived: ev.arrived, rendered: now(), screen: route.screen };
      hmi.renders.push(rec);
      if (hmi.renders.length > 500) hmi.renders.shift();
      hmi.lastRender = rec;
    }
  }

  // -- connection --------------------------------------------------------------------------------
  function setConn(ok) {
    hmi.connected = ok;
    $("#conn-lamp").className = `lamp ${ok ? "on-ok" : "on-fault blink"}`;
    $("#conn-text").textContent = ok ? "live" : "reconnecting";
  }

  function connect() {
    const es = new EventSource("/api/events");
    es.addEventListener("snapshot", (e) => {
      const snap = JSON.parse(e.data);
      CFG = snap.config;
      ST.units = {};
      for (const [name, u] of Object.entries(snap.units)) ST.units[name] = u;
      ST.cell = snap.cell_status;
      route = parseRoute();
      builtUnit = null;
      setConn(true);
      hmi.snapshotAt = now();
      renderAll();
    });
    es.addEventListener("update", (e) => {
      const arrived = now();
      const ev = JSON.parse(e.data);
      ev.arrived = arrived;
      apply(ev);
    });
    es.onopen = () => setConn(true);
    es.onerror = () => setConn(false); // EventSource reconnects by itself and gets a new snapshot
    hmi.source = es;
  }

  window.addEventListener("hashchange", () => {
    route = parseRoute();
    renderAll();
    window.scrollTo(0, 0);
  });

  async function start() {
    const params = new URLSearchParams(location.search);
    const fromUrl = params.get("token");
    if (fromUrl !== null) {
      params.delete("token");
      const rest = params.toString();
      history.replaceState(null, "", `${location.pathname}${rest ? `?${rest}` : ""}${location.hash}`);
    }
    const candidate = fromUrl || token;
    if (candidate) {
      const res = await verifyToken(candidate);
      tokenOk = res.ok;
      token = res.ok ? candidate : "";
      if (res.ok) sessionStorage.setItem(TOKEN_KEY, candidate);
      else {
        sessionStorage.removeItem(TOKEN_KEY);
        accessError = res.message;
      }
    }
    connect();
  }

  start();
})();
