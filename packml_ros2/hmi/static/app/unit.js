// The unit screen: its state diagram (drawn from the unit's compiled rules), commands and modes
// (each one it does not take now says why, in the unit's words the server sends: `why`), lamps,
// machine speed, equipment modules, times, counters, stop reason, OEE and recent transitions.
import { blocked, isLost, lostSince, ownReasons, serverLost } from "./access.js";
import { renderFeedback } from "./actions.js";
import { OPERATOR_STATE, alarmLamp } from "./alarms.js";
import * as D from "../diagram.js";
import { $, $$, CMD_CLASS, COMMANDS, button, esc, fixed, fmtDur, fmtTime, group, modeName, pct, setButton, view } from "./dom.js";
import { recipeLabel } from "./recipe.js";
import { S, ST, conn, pending, unitCfg } from "./store.js";

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
        ${u.recipes?.length ? `<div class="card" id="u-recipe-card"><h2>Recipe <a class="right" id="u-recipe-link" href="#/unit/${encodeURIComponent(name)}/recipe">change, compare →</a></h2><div id="u-recipe"></div></div>` : ""}
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
  $("#u-diagram").appendChild(D.build(u, S.CFG.states));
  S.builtUnit = name;
}

/** Redraw the unit screen; ``parts``: only what these topics change (null: everything). */
export function renderUnit(parts = null) {
  const name = S.route.unit;
  if (S.builtUnit !== name || !$("#diagram")) {
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
  const reasons = ownReasons(x.why || { commands: {}, modes: {}, ems: {} });
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
  else if (s.acting && s.state_requested === s.state) {
    // an acting state that rests in itself (Execute): it ends by State Complete, the unit's
    // rules say where to (this mode's edges from the server), or by a command
    const done = mode?.edges.find(([from, cmd]) => from === s.state_name && !cmd);
    view(prog).html = `<b>${esc(s.state_name)}</b>: producing · leaves by a command${done ? `, or to ${esc(done[2])} when the run is finished (state complete)` : ""}`;
  } else if (s.acting) {
    const waiting = s.equipment_modules.filter((e) => e.active && !e.state_complete).map((e) => e.name);
    view(prog).html = `<b>${esc(s.state_name)}</b> in progress → ${esc(s.state_requested_name)}${waiting.length ? ` · waiting for state complete from ${esc(waiting.join(", "))}` : ""}`;
  } else view(prog).html = `<b>${esc(s.state_name)}</b>: waiting for a command (valid now: ${esc([...valid].join(", ") || "none")})`;

  // commands: valid ones coloured; every other one carries its reason
  const base = blocked(name, "command");
  const refusedByGuard = [];
  for (const b of $$("#u-cmds button")) {
    const c = b.dataset.cmd;
    // the server names every command the unit would not take from this page (one it lists as
    // valid too, under the remote lock); until its reasons follow a new status, valid decides
    const reason = reasons.commands[c];
    const usable = valid.has(c) && !reason;
    const own = usable ? "" : reason?.text || `${c} is not valid now`;
    b.className = `btn cmd${usable && live ? ` valid ${CMD_CLASS[c]}` : ""}${pending.has(`${name}/command/${JSON.stringify({ command: c })}`) ? " pending" : ""}`;
    setButton(b, base || own);
    if (!base && reason?.guard) refusedByGuard.push(`${c}: ${reason.text}`);
  }
  // the reasons of the rule book's guards, not its state model's (the lock, an alarm, a missing
  // EM, an interlock, a mode change)
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

  renderRecipeSummary(name, s);

  // EMs: each one the unit would not switch now says why (the unit's words, from the server)
  $("#u-em-sub").textContent = s ? `state complete for ${s.state_name}` : "";
  const emBase = blocked(name, "set_em_active");
  const rows = (s?.equipment_modules || []).map((e) => {
    const sc = !s.acting || lost ? `<span class="muted">–</span>` : e.active ? (e.state_complete ? `<span class="lamp on-ok"></span> done` : `<span class="lamp on-warn blink"></span> running`) : `<span class="muted">ignored</span>`;
    const flags = [e.blocked ? `<span class="tag warn">blocked</span>` : "", e.starved ? `<span class="tag warn">starved</span>` : ""].join(" ");
    const label = e.active ? "Switch off" : "Switch on";
    const online = lost ? `<span class="lamp"></span> unknown` : `<span class="lamp ${e.online ? "on-ok" : e.active ? "on-fault" : ""}"></span> ${e.online ? "online" : "offline"}`;
    const why = emBase || reasons.ems?.[e.name] || "";
    return `<tr data-em="${esc(e.name)}"><td><b>${esc(e.name)}</b>${e.configured ? "" : ` <span class="tag info">registered</span>`}</td>
      <td>${e.active ? `<span class="tag ok">active</span>` : `<span class="tag">inactive</span>`}</td>
      <td>${online}</td>
      <td>${sc}</td><td>${e.command_request_name ? `<span class="tag bad">${esc(e.command_request_name)}</span> ` : ""}${flags.trim() || (e.command_request_name ? "" : `<span class="muted">–</span>`)}</td>
      <td>${button(label, "set_em_active", { unit: name, args: { em: e.name, active: !e.active }, cls: "small", why })}</td></tr>`;
  });
  view($("#u-ems tbody")).html = rows.join("") || `<tr><td colspan="6" class="empty">no equipment modules</td></tr>`;
}

/** The recipe in use, a changeover running and how the last one ended (the recipe screen has
 *  the rest). */
function renderRecipeSummary(name, s) {
  const el = $("#u-recipe");
  if (!el) return;
  if (!s) {
    view(el).html = `<div class="empty">no status yet</div>`;
    return;
  }
  const change = s.recipe_change_in_process ? ` <span class="tag info">changeover → ${esc(recipeLabel(name, s.recipe_requested))}</span>` : "";
  view(el).html = `<div class="row">In use <b id="u-recipe-current">${esc(recipeLabel(name, s.recipe_current, s.recipe_current_name))}</b>${change}</div>${s.recipe_result ? `<div class="muted small mt-xs">${esc(s.recipe_result)}</div>` : ""}`;
}

function renderUnitAdmin(name, x) {
  const s = x.status, a = x.admin;
  const mode = s?.mode ?? 1;
  const t = a?.times?.[String(mode)];
  const disabled = new Set(unitCfg(name).modes.find((m) => m.number === mode)?.disabled_states || []);
  $("#u-times-mode").textContent = s ? `${s.mode_name} mode` : "";
  if (!t) view($("#u-times")).html = `<div class="empty">no admin data yet</div>`;
  else {
    const rows = S.CFG.states.map((st) => {
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
