// What every screen shares: the page's state, as the server's events left it.
//
// The server sends the configuration (S.CFG: units, states, levels, the rule book's diagrams) in
// its snapshot, then one update per change (ST). Nothing here decides what a unit or the cell
// accepts: the reasons come with the data (a unit's `why`, the cell status' `why`).

/** Knobs and records the browser tests read: the statuses applied to the DOM (renders), the
 * number of updates, whether the page is live, the answers shown (feedback), how long an answer
 * stays in its box (feedbackMs: tests shorten it) and how long without a word from the server (it
 * pings every 5 s) means it is gone (silenceMs). */
export const hmi = (window.__hmi = { renders: [], updates: 0, connected: false, feedback: {}, feedbackMs: 15000, silenceMs: 12000 });

/** The parts of the page's state that are replaced as a whole: the configuration from the last
 * snapshot (CFG), the screen shown (route), the unit whose screen is built (builtUnit) and the
 * one whose recipe screen is (builtRecipe). */
export const S = { CFG: null, route: { screen: "overview", unit: null }, builtUnit: null, builtRecipe: null };

/** The latest of everything the server sent: per unit its status, admin, alarms, transitions,
 * presence and why; the coordinator's cell status and presence. */
export const ST = { units: {}, cell: null, coordinator: null };

export const CRED_KEY = "packml-hmi-credential";

/** Who operates from this page: the credential (a session or the token), the user and level. */
export const me = { credential: sessionStorage.getItem(CRED_KEY) || "", user: "", level: "", error: "" };

/** The connection to the HMI server: live or not, since when, when it was last heard. */
export const conn = { ok: false, since: Date.now(), heard: 0 };

/** Actions sent and not answered yet (their keys), and the alarm history sections the operator
 * opened (kept across redraws). */
export const pending = new Set();
export const historyOpen = new Set();

// The screens register how the page is redrawn (app.js): the modules that change the state
// (access, actions, the stream) redraw through these without importing the screens.
const redraw = { all: () => {}, update: () => {}, feedbacks: () => {} };
export const setRedraw = (fns) => Object.assign(redraw, fns);
export const renderAll = () => redraw.all();
export const renderUpdate = (ev) => redraw.update(ev);
export const renderFeedbacks = () => redraw.feedbacks();

export const unitCfg = (name) => S.CFG.units.find((u) => u.name === name);

/** The screen the address names: #/overview, #/unit/<name>[/recipe], #/alarms[/<name>]. */
export function parseRoute() {
  const parts = location.hash.replace(/^#\/?/, "").split("/").filter(Boolean);
  if (parts[0] === "unit" && parts[1] && S.CFG && unitCfg(decodeURIComponent(parts[1]))) {
    return { screen: parts[2] === "recipe" ? "recipe" : "unit", unit: decodeURIComponent(parts[1]) };
  }
  if (parts[0] === "alarms") return { screen: "alarms", unit: parts[1] ? decodeURIComponent(parts[1]) : null };
  return { screen: "overview", unit: null };
}
