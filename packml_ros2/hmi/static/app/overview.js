// The overview screen: the cell (its state as its units show it, the coordinator, the cell
// commands) and one card per unit.
import { blocked, coordinatorLost, isLost, lostSince } from "./access.js";
import { renderFeedback } from "./actions.js";
import { cellMode, cellState, partsText } from "./banner.js";
import { $, CMD_CLASS, COMMANDS, button, chip, esc, fixed, pct, setHTML, stackLight } from "./dom.js";
import { S, ST, conn } from "./store.js";

/** The cell command buttons: each one the coordinator does not take now says why, in the words
 *  the server sends with the cell status (its `why`: not valid for the units now, a sequence
 *  running); the page adds only what it knows itself (connection, login, level). */
function cellCommands(c) {
  if (!S.CFG.coordinator) return `<span class="muted">no coordinator configured</span>`;
  const base = blocked(null, "command");
  const reasons = c?.why || {};
  return COMMANDS.map((name) => {
    const own = reasons[name] || "";
    return button(name, "command", { args: { command: name }, cls: `cmd ${!own && !base ? `valid ${CMD_CLASS[name]}` : ""}`, why: base || own });
  }).join("");
}

export function renderOverview() {
  const CFG = S.CFG;
  const el = $("#screen-overview");
  const c = ST.cell;
  const online = CFG.units.filter((u) => ST.units[u.name]?.online).length;
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
    <div><div class="muted cell-cmds-title">Cell commands (through the coordinator, in the configured order)</div><div class="cell-cmds" id="cell-cmds">${cellCommands(c)}</div></div>
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
      ${chip(s?.state_name, s?.state, `big${s?.acting && !lost ? " acting" : ""}`)}${s?.stack_light?.colors?.length ? stackLight(s.stack_light) : ""}</div>
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
