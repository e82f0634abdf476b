// Who may act from this page, and why an action cannot be sent now: no connection to the HMI
// server, the unit's or the coordinator's communication lost, not logged in, the level it needs.
// The unit's and the cell's own reasons come from the server with their data (`why`).
import { $, clock, esc, view } from "./dom.js";
import { CRED_KEY, S, ST, conn, hmi, me, renderAll } from "./store.js";

// -- presence ------------------------------------------------------------------------------------
export const presenceOf = (name) => ST.units[name]?.presence;
export const isLost = (name) => presenceOf(name)?.present === false;
export const lostSince = (p) => `COMMUNICATION LOST since ${clock(p.since)}`;
export const coordinatorLost = () => S.CFG.coordinator && ST.coordinator?.present === false;
export const serverLost = () => `NO CONNECTION TO THE HMI SERVER since ${clock(conn.since / 1000)}`;

// -- levels --------------------------------------------------------------------------------------
const loggedIn = () => !!S.CFG && (S.CFG.login === "none" || !!me.user);
const levelNeeded = (unit, action) => (unit ? S.CFG.unit_action_level : S.CFG.cell_action_level)[action] || S.CFG.levels[S.CFG.levels.length - 1];
const levelOk = (needed) => S.CFG.levels.indexOf(me.level) >= S.CFG.levels.indexOf(needed);

/** A unit's reasons (why: every browser gets the same, judged for CFG.why_source, hmi:<user>
 * with logins: the rule book judges every hmi: user alike) in this page's words: its user. */
export function ownReasons(r) {
  if (!(S.CFG.login === "users" && me.user)) return r;
  const own = (text) => String(text).split(S.CFG.why_source).join(`hmi:${me.user}`);
  return {
    commands: Object.fromEntries(Object.entries(r.commands).map(([c, v]) => [c, { ...v, text: own(v.text) }])),
    modes: Object.fromEntries(Object.entries(r.modes).map(([m, text]) => [m, own(text)])),
    ems: Object.fromEntries(Object.entries(r.ems || {}).map(([e, text]) => [e, own(text)])),
    recipe: own(r.recipe || ""),
  };
}

/** Why ``action`` on ``unit`` (null: the cell) cannot be sent from this page now ("": it can). */
export function blocked(unit, action) {
  if (!conn.ok) return serverLost();
  if (unit) {
    const x = ST.units[unit];
    if (isLost(unit)) return `${unit}: ${lostSince(x.presence)} (${x.presence.reason})`;
    if (!x?.status) return `${unit}: no status received yet`;
  } else {
    if (!S.CFG.coordinator) return "no coordinator is configured for this cell";
    if (coordinatorLost()) return `coordinator: ${lostSince(ST.coordinator)} (${ST.coordinator.reason})`;
    if (!ST.cell) return "no status from the coordinator yet";
  }
  if (!loggedIn()) return S.CFG.login === "users" ? "read-only: log in to operate" : "read-only: enter the access token to operate";
  const needed = levelNeeded(unit, action);
  if (!levelOk(needed)) return `needs the ${needed} level (${me.user} is ${me.level})`;
  return "";
}

// -- requests ------------------------------------------------------------------------------------
export async function post(url, body, credential = me.credential) {
  const headers = { "Content-Type": "application/json" };
  if (credential) headers.Authorization = `Bearer ${credential}`;
  try {
    const r = await fetch(url, { method: "POST", headers, body: JSON.stringify(body || {}) });
    return { status: r.status, body: await r.json() };
  } catch (err) {
    return { status: 0, body: { accepted: false, result_name: "NO_CONNECTION", message: `the HMI server did not answer (${err})` } };
  }
}

export function signedIn(credential, body) {
  me.credential = credential;
  me.user = body.user;
  me.level = body.level;
  me.error = "";
  sessionStorage.setItem(CRED_KEY, credential);
}

export function signedOut(error = "") {
  const open = S.CFG && S.CFG.login === "none";
  me.credential = "";
  me.user = open ? "anyone" : "";
  me.level = open ? S.CFG.levels[S.CFG.levels.length - 1] : "";
  me.error = error;
  sessionStorage.removeItem(CRED_KEY);
}

export async function logIn(form) {
  let r;
  if (S.CFG.login === "users") {
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

export async function logOut() {
  if (S.CFG.login === "users") await post("/api/logout", {});
  signedOut();
  hmi.feedback = {};
  renderAll();
}

/** The credential given in the address (?token=, then removed from it) or kept from before,
 * checked with the server once, when the page opens. */
export async function resume() {
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
}

// -- the header's access part and the login dialog -----------------------------------------------
export function renderAccess() {
  const el = $("#access");
  const CFG = S.CFG;
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

export function openLogin() {
  const form = $("#login-form");
  form.innerHTML = S.CFG.login === "users"
    ? `<h3>Log in to operate</h3><label>User <input id="login-user" autocomplete="username" required></label>
       <label>Password <input id="login-password" type="password" autocomplete="current-password" required></label>`
    : `<h3>Access token</h3><label>Token <input id="token-input" type="password" autocomplete="off" aria-label="access token" required></label>`;
  form.insertAdjacentHTML("beforeend", `<div class="err" id="access-error"></div>
    <div class="row end"><button type="button" class="btn" id="login-cancel">Cancel</button><button type="submit" class="btn primary" id="login-submit">${S.CFG.login === "users" ? "Log in" : "Unlock"}</button></div>`);
  $("#login").showModal();
  $("input", form).focus();
}
