// The server's event stream (/api/events): a snapshot (the configuration and everything as it
// is), then one update per change of a unit's status, admin, alarms, transitions, presence
// (online), the reasons why its commands and modes are not available (why), the coordinator's
// cell status and presence. Silence longer than hmi.silenceMs (the server pings every 5 s) or a
// broken stream shows the page as not live; EventSource reconnects by itself.
import { post, signedOut } from "./access.js";
import { $, now } from "./dom.js";
import { S, ST, conn, hmi, me, parseRoute, renderAll, renderUpdate } from "./store.js";

function setConn(ok) {
  if (ok !== conn.ok) conn.since = Date.now();
  conn.ok = ok;
  hmi.connected = ok;
  $("#conn-lamp").className = `lamp ${ok ? "on-ok" : "on-fault blink"}`;
  $("#conn-text").textContent = ok ? "live" : "reconnecting";
  $("#conn").classList.toggle("down", !ok); // (a panel shows the word only when it is news)
}

function heard() {
  conn.heard = Date.now();
  if (!conn.ok && S.CFG) {
    setConn(true);
    renderAll();
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
    const rec = { unit: ev.unit, seq: ev.data.sequence, state: ev.data.state_name, stamp: ev.data.stamp * 1000, received: ev.received, arrived: ev.arrived, rendered: now(), screen: S.route.screen };
    hmi.renders.push(rec);
    if (hmi.renders.length > 500) hmi.renders.shift();
    hmi.lastRender = rec;
  }
}

async function streamUrl() {
  // an operator who has logged in asks for a one-use ticket (EventSource sends no
  // Authorization header): the server keeps streams for operators that others cannot take
  if (!me.credential) return "/api/events";
  const r = await post("/api/events/ticket", {});
  return r.status === 200 ? `/api/events?ticket=${encodeURIComponent(r.body.ticket)}` : "/api/events";
}

export async function connect() {
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
    S.CFG = snap.config;
    ST.units = {};
    for (const [name, u] of Object.entries(snap.units)) ST.units[name] = u;
    ST.cell = snap.cell_status;
    ST.coordinator = snap.coordinator;
    if (S.CFG.login === "none") signedOut();
    S.route = parseRoute();
    S.builtUnit = null;
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
