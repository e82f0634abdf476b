// The header's screen tabs and the banner every screen has: scope, mode, state and the most
// pressing message (the server's connection, a lost unit, an alarm, an unacknowledged one, a
// warning). The cell's state and mode as its units show them.
import { coordinatorLost, isLost, lostSince, presenceOf, serverLost } from "./access.js";
import { $, esc, group, setChip, stackLight, view } from "./dom.js";
import { S, ST, conn } from "./store.js";

function alarmCount(name) {
  const s = ST.units[name]?.status;
  return s ? s.unacknowledged_alarms || s.active_alarms : 0;
}

export function renderNav() {
  const { CFG, route } = S;
  const nav = $("#nav");
  const totalAlarms = CFG.units.reduce((n, u) => n + ((ST.units[u.name]?.alarms?.alarms || []).length), 0);
  const unack = CFG.units.reduce((n, u) => n + (ST.units[u.name]?.status?.unacknowledged_alarms || 0), 0);
  const tabs = [`<a href="#/overview" data-screen="overview" class="${route.screen === "overview" ? "active" : ""}">Overview</a>`];
  for (const u of CFG.units) {
    const s = ST.units[u.name]?.status;
    const active = (route.screen === "unit" || route.screen === "recipe") && route.unit === u.name;
    const lost = isLost(u.name);
    tabs.push(`<a href="#/unit/${encodeURIComponent(u.name)}" data-screen="unit" data-unit="${esc(u.name)}" class="${active ? "active" : ""}${lost ? " lost" : ""}"><span class="dot ${lost ? "lost" : s ? group(s.state_name) : ""}"></span>${esc(u.name)}${lost ? ` <span class="count lost">LOST</span>` : alarmCount(u.name) ? ` <span class="count hot">${alarmCount(u.name)}</span>` : ""}</a>`);
  }
  tabs.push(`<a href="#/alarms" data-screen="alarms" class="${route.screen === "alarms" ? "active" : ""}">Alarms <span class="count ${unack ? "hot" : ""}" id="nav-alarm-count">${totalAlarms}</span></a>`);
  view(nav).html = tabs.join("");
}

export function cellMode() {
  const modes = new Set(S.CFG.units.map((u) => ST.units[u.name]?.status?.mode_name).filter(Boolean));
  if (modes.size === 1) {
    const name = [...modes][0];
    const s = Object.values(ST.units).find((u) => u.status)?.status;
    return `${name} (${s.mode})`;
  }
  return modes.size ? "MIXED" : "–";
}

/** The cell's state as its units show it: their common state, or MIXED with who is where (the
 *  coordinator's aggregate is the most severe state: STOPPED while a unit runs misleads). */
export function cellState() {
  const units = S.CFG.units;
  const parts = new Map();
  for (const u of units) {
    const s = ST.units[u.name]?.status;
    const name = isLost(u.name) ? "LOST" : s ? s.state_name : "NO STATUS";
    if (!parts.has(name)) parts.set(name, []);
    parts.get(name).push(u.name);
  }
  if (parts.size === 1) {
    const name = [...parts.keys()][0];
    const s = ST.units[units[0].name]?.status;
    if (name !== "LOST" && name !== "NO STATUS") return { name, number: s.state, acting: units.some((u) => ST.units[u.name].status.acting), parts };
  }
  return { name: null, parts };
}

export const partsText = (parts) => [...parts.entries()].map(([state, units]) => `${state}: ${units.join(", ")}`).join(" · ");

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

export function renderBanner() {
  const { CFG, route } = S;
  const unit = route.screen === "unit" || route.screen === "recipe" || route.screen === "alarms" ? route.unit : null;
  const modeEl = $("#banner-mode"), stateEl = $("#banner-state"), alarmEl = $("#banner-alarm");
  let message;
  if (unit) {
    const x = ST.units[unit], s = x?.status;
    $("#banner-scope").textContent = unit;
    modeEl.textContent = s ? `${s.mode_name} (${s.mode})` : "–";
    setChip(stateEl, s?.state_name, s?.state, s?.acting && !isLost(unit), isLost(unit) ? "stale" : "");
    message = bannerMessage([unit], false);
    view($("#banner-light")).html = stackLight(s?.stack_light, "stack-light");
    $("#banner-light-item").hidden = !s?.stack_light?.colors?.length;
  } else {
    $("#banner-light-item").hidden = true;
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
