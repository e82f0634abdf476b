// The alarm screen: every unit's alarms and warnings by operator state, with Ack, Acknowledge
// all and Reset, and each unit's alarm history.
import { blocked, isLost, lostSince } from "./access.js";
import { renderFeedback } from "./actions.js";
import { $, $$, button, esc, fmtTime, view } from "./dom.js";
import { S, ST, conn, historyOpen, unitCfg } from "./store.js";

/** The words for an alarm's operator_state (0, 1, 2). */
export const OPERATOR_STATE = ["Active · unacknowledged", "Inactive · unacknowledged", "Acknowledged"];

export function alarmLamp(al) {
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

export function renderAlarms() {
  const { CFG, route } = S;
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
