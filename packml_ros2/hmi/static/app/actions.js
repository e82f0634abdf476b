// Actions: a POST to the server per button, asked twice where it cannot be undone, its answer
// shown in the answer box of its scope (a unit, or the cell) and in a toast.
import { logIn, logOut, openLogin, post, signedOut } from "./access.js";
import { $, $$, esc } from "./dom.js";
import { S, ST, hmi, historyOpen, me, pending, renderAll, renderFeedbacks } from "./store.js";

// The server's answer codes that mean this page's login is no longer good.
const SIGNED_OUT = ["SESSION_ENDED", "TOKEN_WRONG", "TOKEN_MISSING", "LOGIN_REQUIRED"];

// -- confirmation ------------------------------------------------------------------------------
// Abort and the resets of counters, times and alarms are asked twice: they cannot be undone.
function confirmText(unit, action, args) {
  const who = unit || `the whole cell ${S.CFG.title} (every unit at once)`;
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

// -- answers -----------------------------------------------------------------------------------
export function feedback(scope, label, answer, state = "") {
  hmi.feedback[scope] = { label, answer, at: Date.now(), state };
  setTimeout(renderFeedbacks, hmi.feedbackMs + 20);
  renderFeedbacks();
}

export async function act(unit, action, args, label) {
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
  if (r.status === 403 && SIGNED_OUT.includes(answer.code)) signedOut(answer.message);
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
export function renderFeedback(el, scope) {
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

/** Every answer box on the page. */
export function renderAllFeedbacks() {
  renderFeedback($("#u-feedback"), S.route.unit);
  renderFeedback($("#cell-feedback"), "cell");
  for (const f of $$("[data-feedback]")) renderFeedback(f, f.dataset.feedback);
}

// -- the page's clicks and forms ---------------------------------------------------------------
export function listen() {
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
      if (why) feedback(S.route.unit, `Speed ${v}`, { accepted: false, message: why }, "local");
      else act(S.route.unit, "set_mach_speed", { mach_speed: v }, `Speed ${v}`);
    }
  });
}
