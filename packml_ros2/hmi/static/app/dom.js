// Small helpers of every screen: DOM access, escaping, formats, state chips and buttons.
import { unitCfg } from "./store.js";

export const $ = (sel, root = document) => root.querySelector(sel);
export const $$ = (sel, root = document) => Array.from(root.querySelectorAll(sel));

// Replace an element's content only when it changed: buttons under the operator's finger are
// not swapped for equal copies by the updates that keep arriving (a click would get lost).
export function setHTML(el, html) {
  if (el && el.__html !== html) {
    el.innerHTML = html;
    el.__html = html;
  }
}
export const view = (el) => ({ set html(h) { setHTML(el, h); } });

const ESC = { "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" };
export const esc = (s) => String(s ?? "").replace(/[&<>"']/g, (c) => ESC[c]);
export const now = () => performance.timeOrigin + performance.now();

// The colour of a state and of a command button, and the buttons' order: how they look, not
// what they may do (the server says that: a unit's and the cell's `why`).
const GROUP = {
  EXECUTE: "g-run",
  IDLE: "g-ready", STARTING: "g-ready", RESETTING: "g-ready", COMPLETING: "g-ready", COMPLETE: "g-ready",
  HOLDING: "g-pause", HELD: "g-pause", UNHOLDING: "g-pause",
  SUSPENDING: "g-pause", SUSPENDED: "g-pause", UNSUSPENDING: "g-pause",
  STOPPING: "g-stop", STOPPED: "g-stop", CLEARING: "g-stop",
  ABORTING: "g-fault", ABORTED: "g-fault",
};
export const CMD_CLASS = {
  RESET: "c-ready", START: "c-go", STOP: "c-stop", HOLD: "c-pause", UNHOLD: "c-ready",
  SUSPEND: "c-pause", UNSUSPEND: "c-ready", COMPLETE: "c-ready", CLEAR: "c-ready", ABORT: "c-abort",
};
export const COMMANDS = Object.keys(CMD_CLASS);
export const group = (name) => GROUP[name] || "g-none";

export const modeName = (unit, number) => {
  const m = unitCfg(unit)?.modes.find((x) => x.number === number);
  return m ? m.name : `MODE ${number}`;
};
export const pct = (x) => (Number.isFinite(x) ? `${(x * 100).toFixed(1)} %` : "–");
// a number the server could not write (NaN, Infinity: JSON null) shows as a dash
export const fixed = (x, digits) => (Number.isFinite(x) ? x.toFixed(digits) : "–");
export const clock = (t) => new Date(t * 1000).toLocaleTimeString([], { hour12: false });

export function fmtDur(s) {
  s = Math.max(0, Math.floor(s || 0));
  const d = Math.floor(s / 86400), h = Math.floor((s % 86400) / 3600), m = Math.floor((s % 3600) / 60), sec = s % 60;
  const mm = String(m).padStart(2, "0"), ss = String(sec).padStart(2, "0");
  if (d) return `${d}d ${String(h).padStart(2, "0")}:${mm}:${ss}`;
  return `${h}:${mm}:${ss}`;
}

export function fmtTime(t) {
  if (!t) return "–";
  const d = new Date(t * 1000);
  const time = d.toLocaleTimeString([], { hour12: false });
  return d.toDateString() === new Date().toDateString() ? time : `${d.toLocaleDateString()} ${time}`;
}

export function chip(name, number, extra = "") {
  if (!name) return `<span class="state-chip g-none ${extra}">NO STATUS</span>`;
  return `<span class="state-chip ${group(name)} ${extra}">${esc(name)}${number !== undefined ? ` <span class="n">${number}</span>` : ""}</span>`;
}

export function setChip(el, name, number, acting, extra = "") {
  el.className = `state-chip ${name ? group(name) : "g-none"}${acting ? " acting" : ""} ${extra}`;
  el.innerHTML = name ? `${esc(name)}${number !== undefined ? ` <span class="n">${number}</span>` : ""}` : "–";
}

// A button that cannot act now carries why (aria-disabled: it stays tappable, and a tap shows
// the reason instead of sending anything).
export function button(label, act, { unit = "", args = {}, cls = "", why = "", attrs = "", text = label } = {}) {
  return `<button type="button" class="btn ${cls}" data-act="${esc(act)}" data-unit="${esc(unit)}" data-args='${esc(JSON.stringify(args))}' data-label="${esc(label)}" aria-disabled="${why ? "true" : "false"}" data-why="${esc(why)}" ${why ? `title="${esc(why)}"` : ""} ${attrs}>${esc(text)}</button>`;
}

export function setButton(b, why) {
  b.setAttribute("aria-disabled", why ? "true" : "false");
  b.dataset.why = why;
  if (why) b.title = why;
  else b.removeAttribute("title");
}

// A stack light (tower light) as the unit publishes it: its lights top to bottom in their
// configured colours (dim when off, lit, or blinking) and the horn. How it looks, not what it
// means: the unit decides which light is lit (its stack_light configuration).
const LIGHT_MODES = ["off", "on", "blink"];
const LIGHT_COLOURS = new Set(["red", "amber", "yellow", "orange", "green", "blue", "white", "clear"]);
export function stackLight(sl, id = "") {
  const at = id ? ` id="${esc(id)}"` : "";
  if (!sl || !sl.colors?.length) return `<span class="stack-light none"${at} data-lights="" title="no stack light reported">–</span>`;
  const modes = sl.colors.map((_, i) => LIGHT_MODES[sl.modes[i]] || "off");
  const lamps = sl.colors.map((c, i) => `<span class="sl-lamp sl-${LIGHT_COLOURS.has(c) ? c : "other"} ${modes[i]}" data-color="${esc(c)}" data-mode="${modes[i]}"></span>`).join("");
  const lit = sl.colors.map((c, i) => `${c} ${modes[i]}`).join(", ");
  const title = `stack light: ${lit}${sl.horn ? "; horn sounding" : "; horn off"}`;
  return `<span class="stack-light"${at} data-lights="${esc(sl.colors.map((c, i) => `${c}:${modes[i]}`).join(" "))}" data-horn="${sl.horn ? "on" : "off"}" title="${esc(title)}" role="img" aria-label="${esc(title)}"><span class="sl-tower">${lamps}</span><span class="sl-horn ${sl.horn ? "on" : ""}">♪</span></span>`;
}
