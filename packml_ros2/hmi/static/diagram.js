// The PackML state diagram of one unit, drawn from the unit's own compiled rules.
//
// The bridge serves each unit's edges (packml_ros2.core.rules: Rules.edges(), the model's graph
// with the unit's model, hold_from and complete_from; per mode Rules.edges(mode) with skip-through
// and the disabled states). Nothing here says which transitions exist: this file only places the
// 17 states on a grid and routes whatever edges it is given.
//
// - A command that leads from many states to one (Stop, Abort) is drawn as a dashed box around
//   its source states with one arrow into its target; every other edge is routed between the
//   boxes (straight where they are neighbours, else along the gaps between rows and columns,
//   the route with the fewest crossings), labelled with its command (unlabelled: State Complete).
// - update() greys the states the current mode disables, marks the current and target states and
//   lights the edges the unit can take now (its valid commands, or State Complete while acting),
//   through skipped states to where they end.

const NS = "http://www.w3.org/2000/svg";
const W = 896, H = 486;
const CX = [86, 266, 446, 626, 806];
const RY = [72, 152, 232, 342, 444];
const HW = 58, HH = 21;
// The grid: Execute in the middle, the Hold loop above it, the Suspend loop below, Completing to
// the right (Held and Suspended right above and below it: TR88-2022 completes from both), the
// reset path on the left, Stop and Abort at the bottom.
const POS = {
  UNHOLDING: [1, 0], HOLDING: [2, 0], HELD: [3, 0],
  IDLE: [0, 1], STARTING: [1, 1], EXECUTE: [2, 1], COMPLETING: [3, 1], COMPLETE: [4, 1],
  RESETTING: [0, 2], UNSUSPENDING: [1, 2], SUSPENDING: [2, 2], SUSPENDED: [3, 2],
  STOPPED: [0, 3], STOPPING: [1, 3],
  CLEARING: [0, 4], ABORTED: [1, 4], ABORTING: [2, 4],
};
const FAN_IN = 6; // a command leading from this many states or more to one: a box around them
const LEGEND_X = 540, LEGEND_Y = 374;

function svg(tag, attrs = {}, parent = null, text = null) {
  const e = document.createElementNS(NS, tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  if (text !== null) e.textContent = text;
  if (parent) parent.appendChild(e);
  return e;
}

const boxOf = (s) => {
  const [c, r] = POS[s];
  return { s, c, r, cx: CX[c], cy: RY[r], x0: CX[c] - HW, x1: CX[c] + HW, y0: RY[r] - HH, y1: RY[r] + HH };
};
// channels between rows / columns (index i: before row / column i; 0 and n: outside)
const rowGap = (i) => (i <= 0 ? RY[0] - HH - 20 : i >= RY.length ? RY[RY.length - 1] + HH + 14 : (RY[i - 1] + RY[i]) / 2);
const colGap = (i) => (i <= 0 ? CX[0] - HW - 14 : i >= CX.length ? CX[CX.length - 1] + HW + 14 : (CX[i - 1] + CX[i]) / 2);
const label = (cmd) => cmd[0] + cmd.slice(1).toLowerCase();
const keyOf = (from, cmd, to) => `${from}|${cmd || ""}|${to}`;

// -- geometry ------------------------------------------------------------------------------
const segs = (pts) => pts.slice(1).map((p, i) => [pts[i], p]);
const len = (pts) => segs(pts).reduce((n, [a, b]) => n + Math.abs(a[0] - b[0]) + Math.abs(a[1] - b[1]), 0);

function cross(a, b, c, d) {
  // proper intersection of segments ab and cd (touching ends do not count)
  const o = (p, q, r) => Math.sign((q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0]));
  const o1 = o(a, b, c), o2 = o(a, b, d), o3 = o(c, d, a), o4 = o(c, d, b);
  return o1 * o2 < 0 && o3 * o4 < 0;
}

function overlap(a, b, c, d) {
  // parallel axis-aligned segments closer than 10 px sharing more than 6 px of their extent
  const horiz = (p, q) => Math.abs(p[1] - q[1]) < 0.5, vert = (p, q) => Math.abs(p[0] - q[0]) < 0.5;
  const span = (i, p, q, r, s) => Math.min(Math.max(p[i], q[i]), Math.max(r[i], s[i])) - Math.max(Math.min(p[i], q[i]), Math.min(r[i], s[i]));
  if (horiz(a, b) && horiz(c, d)) return Math.abs(a[1] - c[1]) < 9.5 && span(0, a, b, c, d) > 6;
  if (vert(a, b) && vert(c, d)) return Math.abs(a[0] - c[0]) < 9.5 && span(1, a, b, c, d) > 6;
  return false;
}

function hitsBox(p, q, box) {
  const m = 3;
  const x0 = box.x0 - m, x1 = box.x1 + m, y0 = box.y0 - m, y1 = box.y1 + m;
  if (Math.max(p[0], q[0]) < x0 || Math.min(p[0], q[0]) > x1 || Math.max(p[1], q[1]) < y0 || Math.min(p[1], q[1]) > y1) return false;
  // a segment touching the box: inside at an end, or crossing one of its sides
  const inside = (r) => r[0] > x0 && r[0] < x1 && r[1] > y0 && r[1] < y1;
  if (inside(p) || inside(q)) return true;
  const corners = [[x0, y0], [x1, y0], [x1, y1], [x0, y1]];
  return corners.some((c, i) => cross(p, q, c, corners[(i + 1) % 4]));
}

// -- routing -------------------------------------------------------------------------------
// Candidate routes from box a to box b: straight (neighbours), via one row or column channel
// (two bends), via a row and a column channel (three bends); each channel in a few lanes.
const LANES = [0, -9, 9, -18, 18];
const toward = (from, to, d) => (to > from + 0.5 ? d : to < from - 0.5 ? -d : 0);

function candidates(a, b) {
  const out = [];
  const dc = b.c - a.c, dr = b.r - a.r;
  for (const d of [0, -10, 10]) {
    // neighbours in a row or a column: straight (beside one another when two link them)
    if (dr === 0 && Math.abs(dc) === 1) out.push([[dc > 0 ? a.x1 : a.x0, a.cy + d], [dc > 0 ? b.x0 : b.x1, b.cy + d]]);
    if (dc === 0 && Math.abs(dr) === 1) out.push([[a.cx + d, dr > 0 ? a.y1 : a.y0], [b.cx + d, dr > 0 ? b.y0 : b.y1]]);
  }
  if (Math.abs(dc) === 1 && Math.abs(dr) === 1) {
    out.push([[a.cx + 30 * dc, dr > 0 ? a.y1 : a.y0], [b.cx - 30 * dc, dr > 0 ? b.y0 : b.y1]]);
  }
  const ax = (d) => a.cx + toward(a.cx, b.cx, d), bx = (d) => b.cx + toward(b.cx, a.cx, d);
  const ay = (d) => a.cy + toward(a.cy, b.cy, d), by = (d) => b.cy + toward(b.cy, a.cy, d);
  for (let g = 0; g <= RY.length; g++) {
    for (const lane of LANES) {
      const y = rowGap(g) + lane;
      const ya = y < a.cy ? a.y0 : a.y1, yb = y < b.cy ? b.y0 : b.y1;
      out.push([[ax(28), ya], [ax(28), y], [bx(28), y], [bx(28), yb]]);
      for (let k = 0; k <= CX.length; k++) {
        const x = colGap(k) + LANES[(LANES.indexOf(lane) + 1) % LANES.length];
        out.push([[ax(28), ya], [ax(28), y], [x, y], [x, by(13)], [x < b.cx ? b.x0 : b.x1, by(13)]]);
        out.push([[x < a.cx ? a.x0 : a.x1, ay(13)], [x, ay(13)], [x, y], [bx(28), y], [bx(28), yb]]);
      }
    }
  }
  for (let k = 0; k <= CX.length; k++) {
    for (const lane of LANES) {
      const x = colGap(k) + lane;
      out.push([[x < a.cx ? a.x0 : a.x1, ay(13)], [x, ay(13)], [x, by(13)], [x < b.cx ? b.x0 : b.x1, by(13)]]);
    }
  }
  // out of the top or bottom, along a row channel, a column channel and another row channel, in
  // through the top or bottom
  for (let g1 = 0; g1 <= RY.length; g1++) {
    for (let g2 = 0; g2 <= RY.length; g2++) {
      if (g1 === g2) continue;
      for (let k = 0; k <= CX.length; k++) {
        const y1 = rowGap(g1), y2 = rowGap(g2) + 9, x = colGap(k);
        out.push([[ax(28), y1 < a.cy ? a.y0 : a.y1], [ax(28), y1], [x, y1], [x, y2], [bx(28), y2], [bx(28), y2 < b.cy ? b.y0 : b.y1]]);
      }
    }
  }
  return out;
}

// The side of box ``b`` point ``p`` lies on (L, R, T, B), for ports: an edge entering a side
// another one leaves reads as a two-way arrow.
function side(b, p) {
  if (Math.abs(p[0] - b.x0) < 1) return "L";
  if (Math.abs(p[0] - b.x1) < 1) return "R";
  return p[1] < b.cy ? "T" : "B";
}

// How many edges going the other way (``dir``) attach to the same side of box b within 20 px of p.
const clash = (ports, b, p, dir) => ports.filter((x) => x.s === b.s && x.dir === dir && x.side === side(b, p) && Math.abs(x.p[0] - p[0]) + Math.abs(x.p[1] - p[1]) < 20).length;

// The best candidate: no state crossed, then the fewest crossings (the fan-in arrows count half:
// they are the background), bends, length, no way around the sides of the drawing.
function route(a, b, boxes, placed, ports) {
  let best = null, bestScore = Infinity;
  for (const pts of candidates(a, b)) {
    const ss = segs(pts).filter(([p, q]) => p[0] !== q[0] || p[1] !== q[1]);
    if (ss.some(([p, q]) => boxes.some((x) => x.s !== a.s && x.s !== b.s && hitsBox(p, q, x)))) continue;
    // the route must leave a and enter b, not run along or through them
    if (ss.slice(1).some(([p, q]) => hitsBox(p, q, a)) || ss.slice(0, -1).some(([p, q]) => hitsBox(p, q, b))) continue;
    if (pts.some((p) => p[0] < 2 || p[0] > W - 2 || p[1] < 2 || p[1] > H - 2)) continue;
    let score = len(pts) / 30 + ss.length * 12;
    if (pts.some((p) => p[0] < CX[0] - HW || p[0] > CX[CX.length - 1] + HW)) score += 30;
    score += 25 * (clash(ports, a, pts[0], "in") + clash(ports, b, pts[pts.length - 1], "out"));
    for (const [p, q] of ss) {
      for (const [r, s, weight] of placed) {
        if (cross(p, q, r, s)) score += 20 * weight;
        else if (overlap(p, q, r, s)) score += 60;
      }
    }
    if (score < bestScore) [best, bestScore] = [pts, score];
  }
  if (best) {
    ports.push({ s: a.s, side: side(a, best[0]), dir: "out", p: best[0] });
    ports.push({ s: b.s, side: side(b, best[best.length - 1]), dir: "in", p: best[best.length - 1] });
  }
  return best;
}

// A label beside its edge: along the longest segments first, clear of the states and of the
// labels already placed (``taken``: their boxes), else where it least overlaps.
function labelAt(pts, text, boxes, taken) {
  const w = text.length * 6.3 + 4, h = 12;
  const spots = [];
  const ss = segs(pts).sort(([p, q], [r, s]) => Math.abs(r[0] - s[0]) + Math.abs(r[1] - s[1]) - Math.abs(p[0] - q[0]) - Math.abs(p[1] - q[1]));
  for (const [p, q] of ss) {
    for (const t of [0.5, 0.3, 0.7, 0.15, 0.85]) {
      const x = p[0] + (q[0] - p[0]) * t, y = p[1] + (q[1] - p[1]) * t;
      if (Math.abs(p[1] - q[1]) < 0.5) spots.push([x, y - 5, "middle"], [x, y + 13, "middle"]);
      else spots.push([x + 6, y + 4, "start"], [x - 6, y + 4, "end"]);
    }
  }
  const rect = ([x, y, anchor]) => {
    const x0 = anchor === "middle" ? x - w / 2 : anchor === "end" ? x - w : x;
    return { x0, x1: x0 + w, y0: y - h + 2, y1: y + 2 };
  };
  const meets = (a, b) => a.x0 < b.x1 && b.x0 < a.x1 && a.y0 < b.y1 && b.y0 < a.y1;
  let best = spots[0], fewest = Infinity;
  for (const spot of spots) {
    const r = rect(spot);
    if (r.x0 < 2 || r.x1 > W - 2 || r.y0 < 2) continue;
    const n = boxes.filter((b) => meets(r, b)).length * 3 + taken.filter((b) => meets(r, b)).length;
    if (n < fewest) [best, fewest] = [spot, n];
    if (!n) break;
  }
  taken.push(rect(best));
  return best;
}

// -- fan-in commands: a box around the source states ------------------------------------------
// Each row's sources must be one run of neighbouring states (no other state between them) and
// the rows one run too; otherwise the command's edges are drawn one by one.
function region(sources, pad, below) {
  const rows = new Map();
  for (const s of sources) {
    const b = boxOf(s);
    const span = rows.get(b.r) || [b.c, b.c];
    rows.set(b.r, [Math.min(span[0], b.c), Math.max(span[1], b.c)]);
  }
  const order = [...rows.keys()].sort((x, y) => x - y);
  if (order.some((r, i) => i && r !== order[i - 1] + 1)) return null;
  for (const [r, [c0, c1]] of rows) {
    for (const [s, [c, rr]] of Object.entries(POS)) if (rr === r && c >= c0 && c <= c1 && !sources.includes(s)) return null;
  }
  const bands = order.map((r) => ({ r, x0: CX[rows.get(r)[0]] - HW - pad, x1: CX[rows.get(r)[1]] + HW + pad, y0: RY[r] - HH - pad, y1: RY[r] + HH + pad }));
  const right = [], left = [];
  bands.forEach((b, i) => {
    const top = i ? bands[i - 1].y1 : b.y0;
    right.push([b.x1, top], [b.x1, b.y1]);
    left.unshift([b.x0, b.y1], [b.x0, top]);
  });
  const pts = [...right, ...left];
  // where an arrow leaves the box toward a state below it: the bottom at that x
  const exitAt = (x) => {
    let y = null;
    for (const b of bands) if (x >= b.x0 && x <= b.x1) y = b.y1;
    return y;
  };
  return { pts, exitAt, bands, below };
}

// -- building ------------------------------------------------------------------------------
function build(unit, states) {
  const root = svg("svg", { viewBox: `0 0 ${W} ${H}`, id: "diagram", role: "img", "aria-label": `PackML state model of ${unit.name} (model ${unit.model})` });
  const defs = svg("defs", {}, root);
  for (const [id, color] of [["arr", "#9aa7b4"], ["arr-on", "#1f6feb"]]) {
    const m = svg("marker", { id, viewBox: "0 0 10 10", refX: "9", refY: "5", markerWidth: "7", markerHeight: "7", orient: "auto-start-reverse" }, defs);
    svg("path", { d: "M0,0 L10,5 L0,10 z", fill: color }, m);
  }
  const hatch = svg("pattern", { id: "hatch", width: "7", height: "7", patternUnits: "userSpaceOnUse", patternTransform: "rotate(45)" }, defs);
  svg("rect", { width: "7", height: "7", fill: "#f1f3f5" }, hatch);
  svg("line", { x1: "0", y1: "0", x2: "0", y2: "7", stroke: "#dde2e7", "stroke-width": "3" }, hatch);

  const boxes = Object.keys(POS).map(boxOf);
  const layerRegions = svg("g", { class: "regions" }, root);
  const layerEdges = svg("g", { class: "edges" }, root);
  const layerLabels = svg("g", { class: "labels" }, root);

  // group the command edges: one command from many states to one target is a region
  const byCmd = new Map();
  for (const [from, cmd, to] of unit.edges) {
    if (!cmd) continue;
    const k = `${cmd}|${to}`;
    if (!byCmd.has(k)) byCmd.set(k, []);
    byCmd.get(k).push(from);
  }
  const regions = [];
  const fanned = new Set();
  const big = [...byCmd.entries()].filter(([, from]) => from.length >= FAN_IN).sort((x, y) => x[1].length - y[1].length);
  big.forEach(([k, sources], i) => {
    const [cmd, to] = k.split("|");
    const r = region(sources, 8 + 7 * i, to);
    if (!r) return;
    regions.push({ cmd, to, sources, ...r });
    fanned.add(k);
  });

  const placed = []; // segments drawn so far (for crossings), with their weight
  const ports = []; // where edges leave (out) and enter (in) the boxes
  const taken = []; // label boxes placed so far
  const drawn = []; // [key, from, cmd, to] of each element, for update() and tests
  regions.forEach((g, i) => {
    const d = g.pts.map((p, j) => `${j ? "L" : "M"}${p[0]},${p[1]}`).join(" ") + " Z";
    svg("path", { class: `region region-${i}`, d, "data-cmd": g.cmd, "data-to": g.to, "data-sources": g.sources.join(" ") }, layerRegions);
    const t = boxOf(g.to);
    const y = g.exitAt(t.cx) ?? t.y0 - 30;
    const pts = [[t.cx, y], [t.cx, t.y0]];
    const key = keyOf("*", g.cmd, g.to);
    svg("path", { class: "edge fan", d: `M${t.cx},${y} L${t.cx},${t.y0}`, "marker-end": "url(#arr)", "data-key": key, "data-cmd": g.cmd, "data-to": g.to, "data-sources": g.sources.join(" ") }, layerEdges);
    const [lx, ly, anchor] = labelAt(pts, label(g.cmd), boxes, taken);
    svg("text", { class: "edge-label", x: lx, y: ly, "text-anchor": anchor, "data-key": key }, layerLabels, label(g.cmd));
    placed.push(...segs(pts).map(([p, q]) => [p, q, 0.5]));
    for (const s of g.sources) drawn.push([key, s, g.cmd, g.to]);
  });

  // the other edges, nearest first (neighbours, diagonal ones too, get the straight lines); a
  // command and State Complete between the same two states share one arrow ("Complete · SC")
  const far = (e) => Math.max(Math.abs(e.a.c - e.b.c), Math.abs(e.a.r - e.b.r)) * 10 + Math.abs(e.a.c - e.b.c) + Math.abs(e.a.r - e.b.r);
  const pairs = new Map();
  for (const [from, cmd, to] of unit.edges) {
    if (cmd && fanned.has(`${cmd}|${to}`)) continue;
    const k = `${from}|${to}`;
    if (!pairs.has(k)) pairs.set(k, { from, to, cmds: [], a: boxOf(from), b: boxOf(to) });
    pairs.get(k).cmds.push(cmd);
  }
  for (const e of [...pairs.values()].sort((x, y) => far(x) - far(y))) {
    const pts = route(e.a, e.b, boxes, placed, ports) || [[e.a.cx, e.a.cy], [e.b.cx, e.b.cy]];
    const keys = e.cmds.map((c) => keyOf(e.from, c, e.to)).join(" ");
    const named = e.cmds.filter(Boolean);
    const d = pts.map((p, j) => `${j ? "L" : "M"}${p[0]},${p[1]}`).join(" ");
    svg("path", { class: `edge${named.length ? "" : " sc"}`, d, "marker-end": "url(#arr)", "data-key": keys, "data-from": e.from, "data-cmd": named.join(" "), "data-to": e.to }, layerEdges);
    // the commands' names; "SC" beside them when State Complete takes the same arrow
    for (const text of named.length ? [named.map(label).join(" · "), ...(named.length < e.cmds.length ? ["SC"] : [])] : []) {
      const [lx, ly, anchor] = labelAt(pts, text, boxes, taken);
      svg("text", { class: "edge-label", x: lx, y: ly, "text-anchor": anchor, "data-key": keys }, layerLabels, text);
    }
    placed.push(...segs(pts).map(([p, q]) => [p, q, 1]));
    for (const c of e.cmds) drawn.push([keyOf(e.from, c, e.to), e.from, c, e.to]);
  }

  for (const st of states) {
    const b = boxOf(st.name);
    const g = svg("g", { class: `st ${st.acting ? "acting" : "wait"}`, "data-state": st.name, "data-number": st.number, id: `st-${st.name}` }, root);
    const rx = st.acting ? HH : 3;
    svg("rect", { class: "pulse", x: b.x0, y: b.y0, width: 2 * HW, height: 2 * HH, rx }, g);
    svg("rect", { x: b.x0, y: b.y0, width: 2 * HW, height: 2 * HH, rx }, g);
    svg("text", { x: b.cx, y: b.cy + 2 }, g, st.name);
    svg("text", { class: "nr", x: b.cx, y: b.cy + 15 }, g, String(st.number));
    svg("title", {}, g, `${st.number} ${st.name} (${st.acting ? "acting state: left by state complete or a command" : "wait state: left by a command"})`);
  }

  // legend (bottom right): what the marks mean, and each region's command
  const lg = svg("g", { class: "legend" }, root);
  const items = [
    ["current state", (x, y) => svg("rect", { x, y, width: 24, height: 13, rx: 3, fill: "#1565c0", stroke: "#0b1520" }, lg)],
    ["target wait state", (x, y) => svg("rect", { x, y, width: 24, height: 13, rx: 3, fill: "#fff", stroke: "#1f6feb", "stroke-dasharray": "4 3" }, lg)],
    ["acting, in progress", (x, y) => svg("rect", { x, y, width: 24, height: 13, rx: 6.5, fill: "#fff", stroke: "#0b1520", "stroke-dasharray": "5 3" }, lg)],
    ["disabled in this mode", (x, y) => svg("rect", { x, y, width: 24, height: 13, rx: 3, fill: "url(#hatch)", stroke: "#c9d1d9" }, lg)],
    ["possible now", (x, y) => svg("path", { d: `M${x},${y + 6} H${x + 22}`, stroke: "#1f6feb", "stroke-width": 2.4, "marker-end": "url(#arr-on)" }, lg)],
    ["state complete, SC", (x, y) => svg("path", { d: `M${x},${y + 6} H${x + 22}`, stroke: "#9aa7b4", "stroke-width": 1.6, "marker-end": "url(#arr)" }, lg)],
  ];
  regions.forEach((g, i) => {
    items.push([`${label(g.cmd)} from every state in the ${i ? "outer" : "inner"} box`, (x, y) => svg("rect", { x, y, width: 24, height: 13, class: `region region-${i}` }, lg)]);
  });
  items.forEach(([text, draw], i) => {
    // two columns; a region's line is long: one row of its own
    const wide = i >= 6;
    const x = LEGEND_X + (wide ? 0 : (i % 2) * 178), y = LEGEND_Y + (wide ? 3 + (i - 6) : Math.floor(i / 2)) * 19;
    draw(x, y);
    svg("text", { x: x + 32, y: y + 10 }, lg, text);
  });
  root.__drawn = drawn;
  root.__unit = unit.name;
  return root;
}

// -- following the unit --------------------------------------------------------------------
function update(root, unit, s, live, group) {
  const mode = s ? unit.modes.find((m) => m.number === s.mode) : null;
  const disabled = new Set(mode ? mode.disabled_states : []);
  const valid = new Set(s ? s.commands_valid_names : []);
  for (const g of root.querySelectorAll(".st")) {
    const st = g.dataset.state;
    let cls = `st ${g.classList.contains("acting") ? "acting" : "wait"}`;
    if (disabled.has(st)) cls += " disabled";
    if (s && st === s.state_name) cls += ` current ${group(st)}`;
    else if (s && s.state_change_in_process && st === s.state_requested_name) cls += " target";
    g.setAttribute("class", cls);
  }
  // what can happen now: the mode's edges from the current state the unit allows now, each
  // lit along its way (the command's edge, then State Complete through skipped states)
  const lit = new Set();
  if (s && live && mode) {
    for (const [from, cmd, to, skipped] of mode.edges) {
      if (from !== s.state_name || (cmd ? !valid.has(cmd) : !s.acting)) continue;
      const hops = [from, ...skipped, to];
      for (let i = 1; i < hops.length; i++) {
        const c = i === 1 ? cmd : null;
        lit.add(keyOf(hops[i - 1], c, hops[i]));
        if (c) lit.add(keyOf("*", c, hops[i]));
      }
    }
  }
  for (const p of root.querySelectorAll(".edge, .edge-label")) {
    let on = p.dataset.key.split(" ").some((k) => lit.has(k));
    if (on && p.dataset.sources) on = p.dataset.sources.split(" ").includes(s.state_name);
    p.classList.toggle("possible", on);
    if (p.tagName === "path") p.setAttribute("marker-end", on ? "url(#arr-on)" : "url(#arr)");
  }
  for (const r of root.querySelectorAll(".regions .region")) {
    r.classList.toggle("possible", !!s && live && lit.has(keyOf("*", r.dataset.cmd, r.dataset.to)) && r.dataset.sources.split(" ").includes(s.state_name));
  }
}

/** Every edge the drawing shows: [from, command or null, to] (a region: one per source). */
function edgesShown(root) {
  return (root.__drawn || []).map(([, from, cmd, to]) => [from, cmd || null, to]);
}

export { build, update, edgesShown };
