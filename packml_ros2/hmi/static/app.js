// PackML HMI: plain JavaScript, no framework, nothing loaded from elsewhere.
// State arrives on one server-sent-events stream (/api/events): a snapshot, then one update per
// change of a unit's status, admin, alarms, transitions, presence (online), the reasons why
// commands and modes are not available (why), the coordinator's cell status and presence. Actions
// are POSTs to /api/units/<unit>/<action> and /api/cell/<action>; the unit's answer is shown.
//
// Every button that cannot act says why (a title, and in the answer box when tapped): no
// connection to the HMI server, the unit's communication lost, not logged in, the level it needs,
// or the unit's own reason (its rule book, served by the bridge).
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
  const CRED_KEY = "packml-hmi-credential";
  const D = window.PackmlDiagram;

  // -- state -------------------------------------------------------------------------------------
  // feedbackMs: how long the answer to an action stays in its box (tests shorten it)
  // silenceMs: how long without a word from the server (it pings every 5 s) means it is gone
  const hmi = (window.__hmi = { renders: [], updates: 0, connected: false, feedback: {}, feedbackMs: 15000, silenceMs: 12000 });
  let CFG = null;
  const ST = { units: {}, cell: null, coordinator: null };
  let route = { screen: "overview", unit: null };
  // who operates from this page: the credential (a session or the token), the user and level
  const me = { credential: sessionStorage.getItem(CRED_KEY) || "", user: "", level: "", error: "" };
  const conn = { ok: false, since: Date.now(), heard: 0 };
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
  const unitCfg = (name) => CFG.units.find((u) => u.name === name);
  const modeName = (unit, number) => {
    const m = unitCfg(unit)?.modes.find((x) => x.number === number);
    return m ? m.name : `MODE ${number}`;
  };
  const pct = (x) => (Number.isFinite(x) ? `${(x * 100).toFixed(1)} %` : "–");
  // a number the server could not write (NaN, Infinity: JSON null) shows as a dash
  const fixed = (x, digits) => (Number.isFinite(x) ? x.toFixed(digits) : "–");
  const clock = (t) => new Date(t * 1000).toLocaleTimeString([], { hour12: false });

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

  function setChip(el, name, number, acting, extra = "") {
    el.className = `state-chip ${name ? group(name) : "g-none"}${acting ? " acting" : ""} ${extra}`;
    el.innerHTML = name ? `${esc(name)}${number !== undefined ? ` <span class="n">${number}</span>` : ""}` : "–";
  }

  // A button that cannot act now carries why (aria-disabled: it stays tappable, and a tap shows
  // the reason instead of sending anything).
  function button(label, act, { unit = "", args = {}, cls = "", why = "", attrs = "", text = label } = {}) {
    return `<button type="button" class="btn ${cls}" data-act="${esc(act)}" data-unit="${esc(unit)}" data-args='${esc(JSON.stringify(args))}' data-label="${esc(label)}" aria-disabled="${why ? "true" : "false"}" data-why="${esc(why)}" ${why ? `title="${esc(why)}"` : ""} ${attrs}>${esc(text)}</button>`;
  }

  function setButton(b, why) {
    b.setAttribute("aria-disabled", why ? "true" : "false");
    b.dataset.why = why;
    if (why) b.title = why;
    else b.removeAttribute("title");
  }

  // -- presence ----------------------------------------------------------------------------------
  const presenceOf = (name) => ST.units[name]?.presence;
  const isLost = (name) => presenceOf(name)?.present === false;
  const lostSince = (p) => `COMMUNICATION LOST since ${clock(p.since)}`;
  const coordinatorLost = () => CFG.coordinator && ST.coordinator?.present === false;
  const serverLost = () => `NO CONNECTION TO THE HMI SERVER since ${clock(conn.since / 1000)}`;

  // -- access ------------------------------------------------------------------------------------
  const loggedIn = () => !!CFG && (CFG.login === "none" || !!me.user);
  const levelNeeded = (unit, action) => (unit ? CFG.unit_action_level : CFG.cell_action_level)[action] || CFG.levels[CFG.levels.length - 1];
  const levelOk = (needed) => CFG.levels.indexOf(me.level) >= CFG.levels.indexOf(needed);

  /** A unit's reasons (why: every browser gets the same, judged for CFG.why_source, hmi:<user>
   * with logins: the rule book judges every hmi: user alike) in this page's words: its user. */
  function ownReasons(r) {
    if (!(CFG.login === "users" && me.user)) return r;
    const own = (text) => String(text).split(CFG.why_source).join(`hmi:${me.user}`);
    return {
      commands: Object.fromEntries(Object.entries(r.commands).map(([c, v]) => [c, { ...v, text: own(v.text) }])),
      modes: Object.fromEntries(Object.entries(r.modes).map(([m, text]) => [m, own(text)])),
    };
  }

  /** Why ``action`` on ``unit`` (null: the cell) cannot be sent from this page now ("": it can). */
  function blocked(unit, action) {
    if (!conn.ok) return serverLost();
    if (unit) {
      const x = ST.units[unit];
      if (isLost(unit)) return `${unit}: ${lostSince(x.presence)} (${x.presence.reason})`;
      if (!x?.status) return `${unit}: no status received yet`;
    } else {
      if (!CFG.coordinator) return "no coordinator is configured for this cell";
      if (coordinatorLost()) return `coordinator: ${lostSince(ST.coordinator)} (${ST.coordinator.reason})`;
      if (!ST.cell) return "no status from the coordinator yet";
    }
    if (!loggedIn()) return CFG.login === "users" ? "read-only: log in to operate" : "read-only: enter the access token to operate";
    const needed = levelNeeded(unit, action);
    if (!levelOk(needed)) return `needs the ${needed} level (${me.user} is ${me.level})`;
    return "";
  }

  async function post(url, body, credential = me.credential) {
    const headers = { "Content-Type": "application/json" };
    if (credential) headers.Authorization = `Bearer ${credential}`;
    try {
      const r = await fetch(url, { method: "POST", headers, body: JSON.stringify(body || {}) });
      return { status: r.status, body: await r.json() };
    } catch (err) {
      return { status: 0, body: { accepted: false, result_name: "NO_CONNECTION", message: `the HMI server did not answer (${err})` } };
    }
  }

  function signedIn(credential, body) {
    me.credential = credential;
    me.user = body.user;
    me.level = body.level;
    me.error = "";
    sessionStorage.setItem(CRED_KEY, credential);
  }

  function signedOut(error = "") {
    me.credential = "";
    me.user = CFG && CFG.login === "none" ? "anyone" : "";
    me.level = CFG && CFG.login === "none" ? CFG.levels[CFG.levels.length - 1] : "";
    me.error = error;
    sessionStorage.removeItem(CRED_KEY);
  }

  async function logIn(form) {
    let r;
    if (CFG.login === "users") {
      r = await post("/api/login", { user: $("#login-user", form).value.trim(), password: $("#login-password", form).value }, "");
      if (r.status === 200) signedIn(r.body.session, r.body);
    } else {
      const token = $("#token-input", form).value.trim();
      r = await post("/api/auth", {}, token);
      if (r.status === 200) signedIn(token, r.body);
    }
    if (r.status === 200) {
      $("#login").close();
      hmi.feedback = {}; // answers given to someone else
    } else $("#access-error").textContent = r.body.message || "refused";
    renderAll();
  }

  async function logOut() {
    if (CFG.login === "users") await post("/api/logout", {});
    signedOut();
    hmi.feedback = {};
    renderAll();
  }

  function renderAccess() {
    const el = $("#access");
    if (!CFG) return;
    if (CFG.login === "none") {
      view(el).html = `<span class="badge rw" id="access-state" title="no logins configured (hmi.users): whoever opens this page operates">Open access</span>`;
      return;
    }
    if (me.user) {
      const who = CFG.login === "users" ? `${me.user} · ${me.level}` : "Operating";
      view(el).html = `<span class="badge rw" id="access-state" title="every action is recorded as hmi:${esc(me.user)}">${esc(who)}</span><button id="lock-btn" type="button">${CFG.login === "users" ? "Log out" : "Lock"}</button>`;
      return;
    }
    const what = CFG.login === "users" ? "Log in" : "Unlock";
    view(el).html = `<span class="badge ro" id="access-state" title="commands need a login">Read-only</span><button id="login-btn" type="button">${what}</button>${me.error ? `<span class="err" id="access-error-top">${esc(me.error)}</span>` : ""}`;
  }

  function openLogin() {
    const form = $("#login-form");
    form.innerHTML = CFG.login === "users"
      ? `<h3>Log in to operate</h3><label>User <input id="login-user" autocomplete="username" required></label>
         <label>Password <input id="login-password" type="password" autocomplete="current-password" required></label>`
      : `<h3>Access token</h3><label>Token <input id="token-input" type="password" autocomplete="off" aria-label="access token" required></label>`;
    form.insertAdjacentHTML("beforeend", `<div class="err" id="access-error"></div>
      <div class="row end"><button type="button" class="btn" id="login-cancel">Cancel</button><button type="submit" class="btn primary" id="login-submit">${CFG.login === "users" ? "Log in" : "Unlock"}</button></div>`);
    $("#login").showModal();
    $("input", form).focus();
  }

  // -- confirmation ------------------------------------------------------------------------------
  // Abort and the resets of counters, times and alarms are asked twice: they cannot be undone.
  function confirmText(unit, action, args) {
    const who = unit || `the whole cell ${CFG.title} (every unit at once)`;
    if (action === "command" && args.command === "ABORT") return `Abort ${who}? Motion stops at once; the unit needs Clear and Reset to run again.`;
    if (action === "reset_counters") return `Reset the counters of ${unit}? The counts since the last reset are lost (lifetime counts stay).`;
    if (action === "reset_times") return `Reset ${args.scope === "all" ? "all state and mode times" : `the times of the ${ST.units[unit]?.status?.mode_name || "current"} mode`} of ${unit}? The OEE figures start again.`;
    if (action === "reset_alarms") return `Reset the alarms of ${unit}? Acknowledged alarms that are no longer active leave the list.`;
    return "";
  }

  function ask(text) {
    const dlg = $("#confirm");
    $("#confirm-text").textContent = text;
    return new Promise((resolve) => {
      dlg.onclose = () => resolve(dlg.returnValue === "yes");
      dlg.returnValue = "";
      dlg.showModal();
      $("#confirm-no").focus();
    });
  }

  // -- actions -----------------------------------------------------------------------------------
  function feedback(scope, label, answer, state = "") {
    hmi.feedback[scope] = { label, answer, at: Date.now(), state };
    setTimeout(renderFeedbacks, hmi.feedbackMs + 20);
    renderFeedbacks();
  }

  async function act(unit, action, args, label) {
    const text = confirmText(unit, action, args);
    if (text && !(await ask(text))) return null;
    const url = unit ? `/api/units/${encodeURIComponent(unit)}/${action}` : `/api/cell/${action}`;
    const scope = unit || "cell";
    const key = `${scope}/${action}/${JSON.stringify(args)}`;
    pending.add(key);
    feedback(scope, label, { accepted: false, message: `${label} sent, waiting for the answer…` }, "pending");
    const r = await post(url, args);
    pending.delete(key);
    const answer = r.body;
    if (r.status === 403 && ["SESSION_ENDED", "TOKEN_WRONG", "TOKEN_MISSING", "LOGIN_REQUIRED"].includes(answer.code)) signedOut(answer.message);
    feedback(scope, label, answer);
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

  // The box shows the answer to the last action from this page for a few seconds, with when and
  // by whom; then it is empty again (an old answer is not today's news).
  function renderFeedback(el, scope) {
    if (!el) return;
    const f = hmi.feedback[scope];
    el.classList.remove("accepted", "refused", "pending", "local");
    if (!f || Date.now() - f.at > hmi.feedbackMs) {
      el.textContent = "The answer to your last action appears here.";
      el.dataset.state = "empty";
      return;
    }
    const cls = f.state || (f.answer.accepted ? "accepted" : "refused");
    el.classList.add(cls);
    el.dataset.state = cls;
    const code = f.state === "pending" ? "SENT" : f.state === "local" ? "NOT SENT" : f.answer.accepted ? "ACCEPTED" : f.answer.result_name || "REFUSED";
    const stamp = `${new Date(f.at).toLocaleTimeString([], { hour12: false })}${me.user ? ` · ${me.user}` : ""}`;
    el.innerHTML = `<span class="code">${esc(code)}</span>${esc(f.state === "pending" ? f.answer.message : feedbackText(f.label, f.answer))}<span class="when">${esc(stamp)}</span>`;
  }

  function renderFeedbacks() {
    renderFeedback($("#u-feedback"), route.unit);
    renderFeedback($("#cell-feedback"), "cell");
    for (const f of $$("[data-feedback]")) renderFeedback(f, f.dataset.feedback);
  }

  document.addEventListener("click", (e) => {
    const go = e.target.closest("[data-go]");
    if (go && !e.target.closest("button")) {
      location.hash = go.dataset.go;
      return;
    }
    const b = e.target.closest("button[data-act]");
    if (b) {
      const unit = b.dataset.unit || null;
      if (b.getAttribute("aria-disabled") === "true") {
        feedback(unit || "cell", b.dataset.label, { accepted: false, message: b.dataset.why }, "local");
        return;
      }
      act(unit, b.dataset.act, JSON.parse(b.dataset.args || "{}"), b.dataset.label);
      return;
    }
    if (e.target.id === "lock-btn") logOut();
    if (e.target.id === "login-btn") openLogin();
    if (e.target.id === "login-cancel") $("#login").close();
  });
  document.addEventListener("toggle", (e) => {
    const unit = e.target.dataset?.history;
    if (unit !== undefined) e.target.open ? historyOpen.add(unit) : historyOpen.delete(unit);
  }, true);
  document.addEventListener("submit", (e) => {
    if (e.target.method === "dialog") return; // the confirmation dialog closes itself
    e.preventDefault();
    if (e.target.id === "login-form") logIn(e.target);
    if (e.target.id === "speed-form") {
      const why = $("#speed-btn").dataset.why;
      const v = parseFloat($("#speed-input").value);
      if (why) feedback(route.unit, `Speed ${v}`, { accepted: false, message: why }, "local");
      else act(route.unit, "set_mach_speed", { mach_speed: v }, `Speed ${v}`);
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
      const lost = isLost(u.name);
      tabs.push(`<a href="#/unit/${encodeURIComponent(u.name)}" data-screen="unit" data-unit="${esc(u.name)}" class="${active ? "active" : ""}${lost ? " lost" : ""}"><span class="dot ${lost ? "lost" : s ? group(s.state_name) : ""}"></span>${esc(u.name)}${lost ? ` <span class="count lost">LOST</span>` : alarmCount(u.name) ? ` <span class="count hot">${alarmCount(u.name)}</span>` : ""}</a>`);
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

  /** The cell's state as its units show it: their common state, or MIXED with who is where (the
   *  coordinator's aggregate is the most severe state: STOPPED while a unit runs misleads). */
  function cellState() {
    const parts = new Map();
    for (const u of CFG.units) {
      const s = ST.units[u.name]?.status;
      const name = isLost(u.name) ? "LOST" : s ? s.state_name : "NO STATUS";
      if (!parts.has(name)) parts.set(name, []);
      parts.get(name).push(u.name);
    }
    if (parts.size === 1) {
      const name = [...parts.keys()][0];
      const s = ST.units[CFG.units[0].name]?.status;
      if (name !== "LOST" && name !== "NO STATUS") return { name, number: s.state, acting: CFG.units.some((u) => ST.units[u.name].status.acting), parts };
    }
    return { name: null, parts };
  }

  const partsText = (parts) => [...parts.entries()].map(([state, units]) => `${state}: ${units.join(", ")}`).join(" · ");

  function setCellChip(el, c) {
    if (c.name) setChip(el, c.name, c.number, c.acting);
    else {
      el.className = "state-chip g-mixed";
      el.textContent = [...c.parts.keys()].every((k) => k === "LOST") ? "LOST" : "MIXED";
      el.title = partsText(c.parts);
    }
  }

  /** The banner's message for ``units`` (and the coordinator when ``cell``): the HMI server's
   *  connection, a unit's lost communication, an active alarm, an alarm not acknowledged, an
   *  active warning, in that order; else that there is none. */
  function bannerMessage(units, cell) {
    if (!conn.ok) return { cls: "lost", text: `${serverLost()}: the values shown are the last received` };
    const lost = units.filter(isLost);
    if (lost.length) {
      const p = presenceOf(lost[0]);
      return { cls: "lost", text: `${units.length > 1 ? `${lost[0]}: ` : ""}${lostSince(p)} (${p.reason})${lost.length > 1 ? ` · ${lost.length - 1} more unit(s) lost` : ""}` };
    }
    if (cell && coordinatorLost()) return { cls: "lost", text: `Coordinator: ${lostSince(ST.coordinator)} (${ST.coordinator.reason})` };
    const prefix = (name) => (units.length > 1 ? `${name}: ` : "");
    const more = [];
    let first = null;
    for (const name of units) {
      const s = ST.units[name]?.status;
      if (s?.alarm_banner) {
        if (!first) first = { cls: `active${s.unacknowledged_alarms ? " unack" : ""}`, text: `${prefix(name)}${s.alarm_banner}` };
        else more.push(name);
      }
    }
    if (first) return { ...first, text: first.text + (more.length ? ` · alarms on ${more.join(", ")} too` : "") };
    for (const name of units) {
      const s = ST.units[name]?.status;
      const open = (ST.units[name]?.alarms?.alarms || []).filter((a) => !a.acknowledged);
      if (s?.unacknowledged_alarms || open.length) {
        const a = open[0];
        const what = a ? `ALARM ${a.id}/${a.value} ${a.message}` : `${s.unacknowledged_alarms} alarm(s)`;
        return { cls: "unack", text: `${prefix(name)}${what}: cleared, not acknowledged` };
      }
    }
    for (const name of units) {
      const w = (ST.units[name]?.alarms?.warnings || []).find((x) => x.trigger);
      if (w) return { cls: "warn", text: `${prefix(name)}WARNING ${w.id}/${w.value} ${w.message}` };
    }
    return { cls: "ok", text: "No active alarm" };
  }

  function renderBanner() {
    const unit = route.screen === "unit" ? route.unit : route.screen === "alarms" ? route.unit : null;
    const modeEl = $("#banner-mode"), stateEl = $("#banner-state"), alarmEl = $("#banner-alarm");
    let message;
    if (unit) {
      const x = ST.units[unit], s = x?.status;
      $("#banner-scope").textContent = unit;
      modeEl.textContent = s ? `${s.mode_name} (${s.mode})` : "–";
      setChip(stateEl, s?.state_name, s?.state, s?.acting && !isLost(unit), isLost(unit) ? "stale" : "");
      message = bannerMessage([unit], false);
    } else {
      $("#banner-scope").textContent = `Cell ${CFG.title}`;
      modeEl.textContent = cellMode();
      setCellChip(stateEl, cellState());
      message = bannerMessage(CFG.units.map((u) => u.name), true);
    }
    $("#banner").classList.toggle("stale", !conn.ok || (!!unit && isLost(unit)));
    alarmEl.className = `banner-alarm ${message.cls}`;
    const lamp = message.cls === "ok" ? "on-ok" : "";
    view(alarmEl).html = `<span class="lamp ${lamp}"></span><span id="banner-alarm-text">${esc(message.text)}</span>`;
  }

  // -- overview ----------------------------------------------------------------------------------
  function renderOverview() {
    const el = $("#screen-overview");
    const c = ST.cell;
    const online = CFG.units.filter((u) => ST.units[u.name]?.online).length;
    const valid = new Set(CFG.units.flatMap((u) => (isLost(u.name) ? [] : ST.units[u.name]?.status?.commands_valid_names || [])));
    const base = blocked(null, "command");
    const cellCmds = CFG.coordinator
      ? COMMANDS.map((name) => {
          const why = base || (!valid.has(name) ? `${name} is not valid in any unit now` : c.busy && name !== "STOP" && name !== "ABORT" ? `a cell sequence is running (${c.sequence_step || "…"}): only STOP and ABORT` : "");
          return button(name, "command", { args: { command: name }, cls: `cmd ${valid.has(name) && !base ? `valid ${CMD_CLASS[name]}` : ""}`, why });
        }).join("")
      : `<span class="muted">no coordinator configured</span>`;
    const state = cellState();
    const coord = !CFG.coordinator ? "none" : ST.coordinator?.present === false ? lostSince(ST.coordinator) : c ? "running" : "no status yet";
    const cellCard = `<div class="card${!conn.ok ? " stale" : ""}"><div class="cell-card">
      <div><div class="muted">Cell</div><div class="cell-name">${esc(CFG.title)}</div></div>
      <div>
        <div class="row">${state.name ? chip(state.name, state.number, `big${state.acting ? " acting" : ""}`) : `<span class="state-chip big g-mixed" id="cell-state">${[...state.parts.keys()].every((k) => k === "LOST") ? "LOST" : "MIXED"}</span>`}
          ${c?.busy && !coordinatorLost() ? `<span class="tag info">sequence running: ${esc(c.sequence_step || "…")}</span>` : ""}
          ${c && c.lost_units.length && !coordinatorLost() ? `<span class="tag bad">coordinator lost: ${esc(c.lost_units.join(", "))}</span>` : ""}</div>
        <div class="muted mt-xs" id="cell-parts">${state.name ? "" : esc(partsText(state.parts))}</div>
        <div class="cell-meta mt-s">
          <span>Mode <b>${esc(cellMode())}</b></span>
          <span>Units online <b>${online}/${CFG.units.length}</b></span>
          <span id="coordinator-state" class="${coordinatorLost() ? "bad" : ""}">Coordinator <b>${esc(coord)}</b></span>
          ${c?.detail && !coordinatorLost() ? `<span>${esc(c.detail)}</span>` : ""}
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
    const lost = isLost(u.name);
    const summary = ST.cell?.units.find((v) => v.name === u.name);
    const health = lost ? "lost" : !x.online ? "offline" : summary?.health || (s?.active_alarms ? "alarm" : "ok");
    const healthCls = health === "ok" ? "ok" : health === "alarm" || health === "lost" ? "bad" : "warn";
    const ems = s?.equipment_modules || [];
    const sum = (list) => (list || []).reduce((n, c) => n + c.count, 0);
    const processed = sum(a?.counters.processed), defective = sum(a?.counters.defective);
    const emDots = ems.map((e) => `<span class="em-dot"><span class="lamp ${lost || !e.active ? "" : e.online ? "on-ok" : "on-fault"}"></span>${esc(e.name)}</span>`).join("");
    const line = lost
      ? `<div class="alarm-line lost">${esc(lostSince(x.presence))} (${esc(x.presence.reason)}): the values are the last received</div>`
      : `<div class="alarm-line ${s?.alarm_banner ? "active" : ""}">${esc(s?.alarm_banner || "No active alarm")}</div>`;
    return `<div class="card unit-card${lost || !conn.ok ? " stale" : ""}" data-go="#/unit/${encodeURIComponent(u.name)}" data-unit-card="${esc(u.name)}">
      <div class="head"><div><div class="name">${esc(u.name)}</div><div class="desc">${esc(u.description)}</div></div>
        ${chip(s?.state_name, s?.state, `big${s?.acting && !lost ? " acting" : ""}`)}</div>
      <div class="facts">
        <div class="fact"><div class="k">Mode</div><div class="v">${esc(s?.mode_name || "–")}</div></div>
        <div class="fact"><div class="k">Health</div><div class="v"><span class="tag ${healthCls}">${esc(health)}</span></div></div>
        <div class="fact"><div class="k">EMs online</div><div class="v">${lost ? "?" : ems.filter((e) => e.online).length}/${ems.length}</div></div>
        <div class="fact"><div class="k">Speed</div><div class="v">${s ? `${fixed(s.cur_mach_speed, 0)}/${fixed(s.mach_speed, 0)}` : "–"}</div></div>
        <div class="fact"><div class="k">Processed</div><div class="v">${processed}</div></div>
        <div class="fact"><div class="k">Defective</div><div class="v">${defective}</div></div>
        <div class="fact"><div class="k">Alarms</div><div class="v">${s?.active_alarms ?? 0}</div></div>
        <div class="fact"><div class="k">OEE</div><div class="v">${a ? pct(a.oee.oee) : "–"}</div></div>
      </div>
      <div class="bar" id="oee-${esc(u.name)}"><i></i></div>
      <div class="em-dots">${emDots || `<span class="muted">no equipment modules</span>`}</div>
      ${line}
    </div>`;
  }

  // -- unit screen -------------------------------------------------------------------------------
  function buildUnit(name) {
    const el = $("#screen-unit");
    const u = unitCfg(name);
    el.innerHTML = `
      <div class="grid cols-unit">
        <div class="stack tight">
          <div class="card diagram"><h2>State model <span class="sub" id="u-model-sub"></span><span class="right muted" id="u-seq"></span></h2>
            <div class="diagram-box"><div id="u-diagram"></div><div class="lost-note" id="u-lost" hidden></div></div>
            <div class="progress-line" id="u-progress"></div></div>
          <div class="card"><h2>Commands <span class="sub">a grey one says why when tapped</span></h2>
            <div class="cmds" id="u-cmds">${COMMANDS.map((c) => button(c, "command", { unit: name, args: { command: c }, cls: "cmd", why: "…", attrs: `data-cmd="${c}"` })).join("")}</div>
            <div class="why-line" id="u-why"></div>
            <div class="feedback" id="u-feedback"></div><div class="readonly-note" id="u-ro"></div></div>
        </div>
        <div class="stack tight">
          <div class="card"><h2>Unit mode <span class="right" id="u-mode-now"></span></h2>
            <div class="modes" id="u-modes">${u.modes.map((m) => button(`Mode ${m.name}`, "set_mode", { unit: name, args: { mode: m.number }, cls: "mode-btn", why: "…", attrs: `data-mode="${m.number}"`, text: m.name })).join("")}</div>
            <div class="why-line" id="u-mode-why"></div>
            <div class="lamps" id="u-lamps"></div>
            <form class="speed" id="speed-form"><span class="muted">Machine speed</span><input id="speed-input" type="number" step="any" min="0" aria-label="machine speed setpoint"><button class="btn small" id="speed-btn" type="submit">Set</button><span class="muted" id="u-speed"></span></form>
          </div>
          <div class="card"><h2>Alarms <a class="right" href="#/alarms/${encodeURIComponent(name)}">alarm list →</a></h2><div id="u-alarms"></div></div>
          <div class="card"><h2>Equipment modules <span class="sub" id="u-em-sub"></span></h2>
            <div class="table-wrap"><table id="u-ems"><thead><tr><th>EM</th><th>Active</th><th>Online</th><th>State complete</th><th>Request / interlock</th><th></th></tr></thead><tbody></tbody></table></div>
            <div class="readonly-note">Switching an EM active/inactive is allowed outside Production only, and logged.</div></div>
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
    $("#u-diagram").appendChild(D.build(u, CFG.states));
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
    $("#screen-unit").classList.toggle("stale", isLost(name) || !conn.ok);
    if (all || parts.has("status") || parts.has("why")) renderUnitStatus(name, x);
    if (all || parts.has("status") || parts.has("admin")) renderUnitAdmin(name, x);
    if (all || parts.has("alarms") || parts.has("status")) renderUnitAlarms(name, x);
    if (all || parts.has("transition")) renderTransitions(x);
    renderFeedback($("#u-feedback"), name);
  }

  function renderUnitStatus(name, x) {
    const s = x.status;
    const u = unitCfg(name);
    const lost = isLost(name);
    const live = !lost && conn.ok;
    const valid = new Set(s?.commands_valid_names || []);
    const reasons = ownReasons(x.why || { commands: {}, modes: {} });
    D.update($("#diagram"), u, s, live, group);
    const mode = s ? u.modes.find((m) => m.number === s.mode) : null;
    $("#u-model-sub").textContent = `TR88-${u.model}${s ? ` · ${s.mode_name} · ${mode ? mode.disabled_states.length : 0} disabled` : ""}`;
    $("#u-seq").textContent = s ? `transition #${s.sequence}` : "";
    const note = $("#u-lost");
    note.hidden = live;
    note.textContent = !conn.ok ? serverLost() : lost ? `${lostSince(x.presence)} · ${x.presence.reason}` : "";
    const prog = $("#u-progress");
    if (!conn.ok) view(prog).html = `<b>${esc(serverLost())}</b>: the last received state is shown`;
    else if (lost) view(prog).html = `<b>${esc(lostSince(x.presence))}</b>: last known state ${esc(s?.state_name || "–")}; commands are disabled until the unit is back`;
    else if (!s) prog.textContent = x.presence?.present === null ? "Waiting for the unit…" : "No status from this unit (is it running?)";
    else if (s.state_name === "EXECUTE") {
      view(prog).html = `<b>EXECUTE</b>: producing · leaves by a command, or to COMPLETING when the run is finished (state complete)`;
    } else if (s.acting) {
      const waiting = s.equipment_modules.filter((e) => e.active && !e.state_complete).map((e) => e.name);
      view(prog).html = `<b>${esc(s.state_name)}</b> in progress → ${esc(s.state_requested_name)}${waiting.length ? ` · waiting for state complete from ${esc(waiting.join(", "))}` : ""}`;
    } else view(prog).html = `<b>${esc(s.state_name)}</b>: waiting for a command (valid now: ${esc([...valid].join(", ") || "none")})`;

    // commands: valid ones coloured; every other one carries its reason
    const base = blocked(name, "command");
    const refusedByGuard = [];
    for (const b of $$("#u-cmds button")) {
      const c = b.dataset.cmd;
      // a command the unit lists as valid is still refused to this page by the remote lock
      const usable = valid.has(c) && reasons.commands[c]?.reason !== "REMOTE_DISABLED";
      const own = usable ? "" : reasons.commands[c]?.text || `${c} is not valid now`;
      b.className = `btn cmd${usable && live ? ` valid ${CMD_CLASS[c]}` : ""}${pending.has(`${name}/command/${JSON.stringify({ command: c })}`) ? " pending" : ""}`;
      setButton(b, base || own);
      const reason = reasons.commands[c]?.reason;
      if (!base && reason && reason !== "COMMAND_NOT_ALLOWED" && reason !== "STATE_DISABLED") refusedByGuard.push(`${c}: ${reasons.commands[c].text}`);
    }
    // the reasons that are not the state model's (an alarm, a missing EM, an interlock, a mode change)
    view($("#u-why")).html = refusedByGuard.length ? `<span class="tag warn">not now</span> ${esc(refusedByGuard[0])}${refusedByGuard.length > 1 ? ` <span class="muted">(+${refusedByGuard.length - 1} more)</span>` : ""}` : "";
    $("#u-ro").textContent = base && !s ? "" : base;

    // mode
    const modeBase = blocked(name, "set_mode");
    for (const b of $$("#u-modes button")) {
      const m = +b.dataset.mode;
      b.classList.toggle("current", !!s && m === s.mode);
      b.classList.toggle("requested", !!s && s.mode_change_in_process && m === s.mode_requested);
      setButton(b, modeBase || reasons.modes[String(m)] || "");
    }
    const modeWhy = s && !modeBase ? u.modes.filter((m) => m.number !== s.mode && reasons.modes[String(m.number)]).map((m) => reasons.modes[String(m.number)]) : [];
    $("#u-mode-why").textContent = modeWhy.length ? modeWhy[0] : "";
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
    const speedWhy = blocked(name, "set_mach_speed");
    speedInput.disabled = !!speedWhy;
    setButton($("#speed-btn"), speedWhy);
    $("#u-speed").textContent = s ? `actual ${fixed(s.cur_mach_speed, 1)}${u.mach_design_speed ? ` · design ${u.mach_design_speed}` : ""}` : "";

    // EMs
    const inProduction = s?.mode === 1;
    $("#u-em-sub").textContent = s ? `state complete for ${s.state_name}` : "";
    const emBase = blocked(name, "set_em_active");
    const rows = (s?.equipment_modules || []).map((e) => {
      const sc = !s.acting || lost ? `<span class="muted">–</span>` : e.active ? (e.state_complete ? `<span class="lamp on-ok"></span> done` : `<span class="lamp on-warn blink"></span> running`) : `<span class="muted">ignored</span>`;
      const flags = [e.blocked ? `<span class="tag warn">blocked</span>` : "", e.starved ? `<span class="tag warn">starved</span>` : ""].join(" ");
      const label = e.active ? "Switch off" : "Switch on";
      const online = lost ? `<span class="lamp"></span> unknown` : `<span class="lamp ${e.online ? "on-ok" : e.active ? "on-fault" : ""}"></span> ${e.online ? "online" : "offline"}`;
      const why = emBase || (inProduction ? `${label} ${e.name}: EMs are switched outside PRODUCTION only` : "");
      return `<tr data-em="${esc(e.name)}"><td><b>${esc(e.name)}</b>${e.configured ? "" : ` <span class="tag info">registered</span>`}</td>
        <td>${e.active ? `<span class="tag ok">active</span>` : `<span class="tag">inactive</span>`}</td>
        <td>${online}</td>
        <td>${sc}</td><td>${e.command_request_name ? `<span class="tag bad">${esc(e.command_request_name)}</span> ` : ""}${flags.trim() || (e.command_request_name ? "" : `<span class="muted">–</span>`)}</td>
        <td>${button(label, "set_em_active", { unit: name, args: { em: e.name, active: !e.active }, cls: "small", why })}</td></tr>`;
    });
    view($("#u-ems tbody")).html = rows.join("") || `<tr><td colspan="6" class="empty">no equipment modules</td></tr>`;
  }

  function renderUnitAdmin(name, x) {
    const s = x.status, a = x.admin;
    const mode = s?.mode ?? 1;
    const t = a?.times?.[String(mode)];
    const disabled = new Set(unitCfg(name).modes.find((m) => m.number === mode)?.disabled_states || []);
    $("#u-times-mode").textContent = s ? `${s.mode_name} mode` : "";
    if (!t) view($("#u-times")).html = `<div class="empty">no admin data yet</div>`;
    else {
      const rows = CFG.states.map((st) => {
        const cls = s && st.number === s.state ? "current-row" : disabled.has(st.name) ? "disabled-row" : "";
        return `<tr class="${cls}"><td>${esc(st.name)}</td><td class="num">${fmtDur(t.state_current[st.number])}</td><td class="num">${fmtDur(t.state_cumulative[st.number])}</td></tr>`;
      });
      view($("#u-times")).html = `<dl class="kv"><dt>In this mode since entry</dt><dd class="num" id="t-mode-current">${fmtDur(t.mode_current)}</dd>
        <dt>In this mode, cumulative</dt><dd class="num">${fmtDur(t.mode_cumulative)}</dd>
        <dt>Since reset of all times</dt><dd class="num">${fmtDur(a.acc_time_since_reset)}</dd></dl>
        <table class="mt-s"><thead><tr><th>State</th><th class="num">Current</th><th class="num">Cumulative</th></tr></thead><tbody>${rows.join("")}</tbody></table>`;
    }
    const timesWhy = blocked(name, "reset_times");
    view($("#u-time-keys")).html =
      button("Reset times of this mode", "reset_times", { unit: name, args: { scope: "mode" }, cls: "small", why: timesWhy }) +
      button("Reset all times", "reset_times", { unit: name, args: { scope: "all" }, cls: "small", why: timesWhy });

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
    view($("#u-counter-keys")).html = button("Reset counters", "reset_counters", { unit: name, cls: "small", why: blocked(name, "reset_counters") });

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
    const rows = list.slice(0, 3).map((al) => `<tr class="al-${al.operator_state}${al.trigger ? " still" : ""}"><td class="first"><span class="lamp ${alarmLamp(al)}"></span></td><td>${al.id}/${al.value}</td><td class="msg">${esc(al.message)}</td><td>${esc(OPERATOR_STATE[al.operator_state] || "")}</td></tr>`);
    view($("#u-alarms")).html = `<div class="row"><span>Active <b>${s?.active_alarms ?? 0}</b></span><span>Unacknowledged <b>${s?.unacknowledged_alarms ?? 0}</b></span>
      ${x.alarms?.first_out ? `<span class="muted">first out: ${esc(`${x.alarms.first_out.id}/${x.alarms.first_out.value} ${x.alarms.first_out.message}`)}</span>` : ""}</div>
      ${rows.length ? `<table class="alarm-table mt-s"><tbody>${rows.join("")}</tbody></table>` : ""}
      ${list.length > 3 ? `<div class="muted">… ${list.length - 3} more in the alarm list</div>` : ""}`;
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

  function alarmRows(unit, list, why) {
    return list
      .map((al) => `<tr class="${al.kind === "warning" ? "warning-row" : `al-${al.operator_state}`}${al.trigger ? " still" : ""}" data-alarm="${al.id}/${al.value}" data-operator-state="${al.operator_state}">
        <td class="first"><span class="lamp ${alarmLamp(al)}"></span></td>
        <td>${al.kind === "warning" ? (al.trigger ? "Warning · active" : "Warning · cleared") : esc(OPERATOR_STATE[al.operator_state] || "")}${al.kind !== "warning" && al.operator_state === 2 && al.trigger ? ` <span class="tag bad">still active</span>` : ""}</td>
        <td class="num">${al.id}/${al.value}</td><td class="num">${al.category}</td><td class="msg">${esc(al.message)}</td>
        <td>${esc(al.em || "–")}</td><td class="muted">${esc(al.source)}</td><td>${fmtTime(al.time)}</td><td>${fmtTime(al.ack_time)}</td><td>${fmtTime(al.cleared_time)}</td>
        <td>${al.reaction_name ? `<span class="tag">${esc(al.reaction_name)}</span>` : "–"}</td>
        <td>${al.kind === "alarm" ? button("Ack", "ack_alarms", { unit, args: { all: false, id: al.id, value: al.value }, cls: "small", why: why || (al.acknowledged ? "already acknowledged" : "") }) : ""}</td></tr>`)
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
      const lost = isLost(u.name);
      const ackWhy = blocked(u.name, "ack_alarms"), resetWhy = blocked(u.name, "reset_alarms");
      const list = x.alarms?.alarms || [], warnings = x.alarms?.warnings || [];
      const unack = list.filter((a) => !a.acknowledged).length;
      const history = (x.admin?.history || []).slice(0, 15);
      return `<div class="card${lost || !conn.ok ? " stale" : ""}" data-alarm-unit="${esc(u.name)}"><h2>${esc(u.name)} <span class="sub">${list.length} alarm(s), ${unack} unacknowledged, ${warnings.length} warning(s)</span>
          <span class="right row">${button("Acknowledge all", "ack_alarms", { unit: u.name, args: { all: true }, cls: "small", why: ackWhy || (unack ? "" : "no alarm to acknowledge") })}
          ${button("Reset alarms", "reset_alarms", { unit: u.name, cls: "small", why: resetWhy || (list.length ? "" : "no alarm to reset") })}</span></h2>
        ${lost ? `<div class="lost-line">${esc(lostSince(x.presence))} (${esc(x.presence.reason)}): the list is the last received</div>` : ""}
        ${list.length ? `<table class="alarm-table"><thead>${head}</thead><tbody>${alarmRows(u.name, list, ackWhy)}</tbody></table>` : `<div class="empty">No alarms</div>`}
        ${warnings.length ? `<h3 class="sub-head">Warnings <span class="muted">(no acknowledgement; they never change the state)</span></h3><table class="alarm-table"><thead>${head}</thead><tbody>${alarmRows(u.name, warnings, ackWhy)}</tbody></table>` : ""}
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
    document.body.classList.toggle("offline", !conn.ok);
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
      if (topic !== "transition" && topic !== "why") renderOverview();
    } else if (route.screen === "unit") {
      if (ev.unit === route.unit) renderUnit(topic === "online" ? null : new Set([topic]));
    } else if (route.screen === "alarms" && topic !== "transition" && topic !== "cell" && topic !== "why") {
      if (!route.unit || ev.unit === route.unit) renderAlarms();
    }
  }

  function apply(ev) {
    hmi.updates++;
    if (ev.topic === "cell") ST.cell = ev.data;
    else if (ev.topic === "coordinator") ST.coordinator = ev.data;
    else {
      const u = (ST.units[ev.unit] ||= { status: null, admin: null, alarms: null, transitions: [], online: false, presence: null, why: null });
      if (ev.topic === "transition") {
        u.transitions.push(ev.data);
        if (u.transitions.length > 30) u.transitions.shift();
      } else if (ev.topic === "online") {
        u.presence = ev.data;
        u.online = ev.data.present === true;
      } else u[ev.topic] = ev.data;
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
    if (ok !== conn.ok) conn.since = Date.now();
    conn.ok = ok;
    hmi.connected = ok;
    $("#conn-lamp").className = `lamp ${ok ? "on-ok" : "on-fault blink"}`;
    $("#conn-text").textContent = ok ? "live" : "reconnecting";
    $("#conn").classList.toggle("down", !ok);  // (a panel shows the word only when it is news)
  }

  function heard() {
    conn.heard = Date.now();
    if (!conn.ok && CFG) {
      setConn(true);
      renderAll();
    }
  }

  async function streamUrl() {
    // an operator who has logged in asks for a one-use ticket (EventSource sends no
    // Authorization header): the server keeps streams for operators that others cannot take
    if (!me.credential) return "/api/events";
    const r = await post("/api/events/ticket", {});
    return r.status === 200 ? `/api/events?ticket=${encodeURIComponent(r.body.ticket)}` : "/api/events";
  }

  async function connect() {
    const es = new EventSource(await streamUrl());
    setInterval(() => {
      if (conn.ok && Date.now() - conn.heard > hmi.silenceMs) {
        setConn(false);
        renderAll();
      }
    }, 500);
    es.addEventListener("ping", heard);
    es.addEventListener("snapshot", (e) => {
      conn.heard = Date.now();
      const snap = JSON.parse(e.data);
      CFG = snap.config;
      ST.units = {};
      for (const [name, u] of Object.entries(snap.units)) ST.units[name] = u;
      ST.cell = snap.cell_status;
      ST.coordinator = snap.coordinator;
      if (CFG.login === "none") signedOut();
      route = parseRoute();
      builtUnit = null;
      setConn(true);
      hmi.snapshotAt = now();
      renderAll();
    });
    es.addEventListener("update", (e) => {
      heard();
      const arrived = now();
      const ev = JSON.parse(e.data);
      ev.arrived = arrived;
      apply(ev);
    });
    es.onopen = () => heard();
    es.onerror = () => {
      // EventSource reconnects by itself and gets a new snapshot; meanwhile nothing shown is live
      const was = conn.ok;
      setConn(false);
      if (was) renderAll();
    };
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
    const candidate = fromUrl || me.credential;
    if (candidate) {
      const r = await post("/api/auth", {}, candidate);
      if (r.status === 200 && r.body.user !== "anyone") signedIn(candidate, r.body);
      else {
        sessionStorage.removeItem(CRED_KEY);
        me.credential = "";
        if (r.status !== 200) me.error = r.body.message;
      }
    }
    connect();
  }

  start();
})();
