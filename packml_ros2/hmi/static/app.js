// PackML HMI: plain JavaScript modules, no framework, no build step, nothing loaded from
// elsewhere. This file wires the screens; each lives in a module of its own under app/:
//
//   store.js     the page's state (what the server sent, who operates, the connection)
//   stream.js    the server's event stream: a snapshot, then one update per change
//   access.js    logins, levels, and why an action cannot be sent from this page now
//   actions.js   the POSTs of the buttons, their confirmation and answer boxes
//   banner.js    the header's tabs and the banner every screen has
//   overview.js  the cell and a card per unit
//   unit.js      one unit: state diagram (../diagram.js), commands, modes, EMs, records
//   recipe.js    one unit's recipes: compare, change, the changeover per EM, its result
//   alarms.js    the alarm list
//
// Every button that cannot act says why (a title, and in the answer box when tapped). What a
// unit or the cell accepts is never decided here: the unit's reasons (its rule book, served by
// the bridge as `why`) and the cell's (the cell status' `why`) come from the server; the page
// adds only what it knows itself: no connection to the HMI server, a unit's communication lost,
// not logged in, the level an action needs.
import { renderAccess, resume } from "./app/access.js";
import { listen, renderAllFeedbacks } from "./app/actions.js";
import { renderAlarms } from "./app/alarms.js";
import { renderBanner, renderNav } from "./app/banner.js";
import { $ } from "./app/dom.js";
import { renderOverview } from "./app/overview.js";
import { renderRecipe } from "./app/recipe.js";
import { S, conn, parseRoute, setRedraw } from "./app/store.js";
import { connect } from "./app/stream.js";
import { renderUnit } from "./app/unit.js";

const SCREENS = ["overview", "unit", "recipe", "alarms"];

function renderAll() {
  const { CFG, route } = S;
  if (!CFG) return;
  document.title = `${CFG.title} · PackML HMI`;
  $("#title").textContent = `PackML HMI · ${CFG.title}`;
  document.body.classList.toggle("offline", !conn.ok);
  for (const s of SCREENS) $(`#screen-${s}`).hidden = s !== route.screen;
  renderAccess();
  renderNav();
  renderBanner();
  if (route.screen === "overview") renderOverview();
  else if (route.screen === "unit") renderUnit();
  else if (route.screen === "recipe") renderRecipe();
  else renderAlarms();
}

/** Redraw what update ``ev`` changes on the screen shown. */
function renderUpdate(ev) {
  const { route } = S;
  const topic = ev.topic;
  renderBanner();
  if (topic === "status" || topic === "alarms" || topic === "online") renderNav();
  if (route.screen === "overview") {
    if (topic !== "transition" && topic !== "why") renderOverview();
  } else if (route.screen === "unit") {
    if (ev.unit === route.unit) renderUnit(topic === "online" ? null : new Set([topic]));
  } else if (route.screen === "recipe") {
    if (ev.unit === route.unit && topic !== "admin" && topic !== "transition") renderRecipe();
  } else if (route.screen === "alarms" && topic !== "transition" && topic !== "cell" && topic !== "why") {
    if (!route.unit || ev.unit === route.unit) renderAlarms();
  }
}

setRedraw({ all: renderAll, update: renderUpdate, feedbacks: renderAllFeedbacks });
listen();
window.addEventListener("hashchange", () => {
  S.route = parseRoute();
  renderAll();
  window.scrollTo(0, 0);
});

await resume();
connect();
