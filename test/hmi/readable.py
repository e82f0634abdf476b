"""What a page must be at any size: readable (WCAG 2.1 AA contrast of every visible text) and
whole (nothing wider than the window, no command row cut). Measured in the browser, from the
computed styles, the way a contrast checker does it.

Contrast (WCAG 2.1 1.4.3): the relative luminance of the text colour and of the background
behind it; 4.5:1, or 3:1 for large text (24 px, or 18.66 px bold). The background is the
nearest painted one: for HTML text its ancestors' background colours composed over one
another, for SVG text the shape drawn under it (or its halo: ``paint-order: stroke``), both
with their alphas; an element's own opacity and its ancestors' fade the text into that
background. Inactive controls (disabled, ``aria-disabled``) are exempt, as WCAG says.
"""

from __future__ import annotations

from typing import Any

CONTRAST_JS = r"""
() => {
  const parse = (c) => {
    const m = c && c.match(/rgba?\(([^)]+)\)/);
    if (!m) return null;
    const p = m[1].split(/[ ,/]+/).filter(Boolean).map(Number);
    return { r: p[0], g: p[1], b: p[2], a: p.length > 3 ? p[3] : 1 };
  };
  const over = (top, bottom) => {
    const a = top.a + bottom.a * (1 - top.a);
    if (a === 0) return { r: 0, g: 0, b: 0, a: 0 };
    const mix = (k) => (top[k] * top.a + bottom[k] * bottom.a * (1 - top.a)) / a;
    return { r: mix("r"), g: mix("g"), b: mix("b"), a };
  };
  const lum = (c) => {
    const f = (v) => { v /= 255; return v <= 0.03928 ? v / 12.92 : ((v + 0.055) / 1.055) ** 2.4; };
    return 0.2126 * f(c.r) + 0.7152 * f(c.g) + 0.0722 * f(c.b);
  };
  const ratio = (a, b) => { const x = lum(a), y = lum(b); return (Math.max(x, y) + 0.05) / (Math.min(x, y) + 0.05); };
  const WHITE = { r: 255, g: 255, b: 255, a: 1 };
  const htmlBackground = (el) => {
    const layers = [];
    for (let e = el; e && e.nodeType === 1; e = e.parentElement) {
      if (e instanceof SVGElement && !(e instanceof SVGSVGElement)) continue;
      const c = parse(getComputedStyle(e).backgroundColor);
      if (c && c.a > 0) { layers.push(c); if (c.a >= 1) break; }
    }
    let bg = WHITE;
    for (const c of layers.reverse()) bg = over(c, bg);
    return bg;
  };
  const svgBackground = (el) => {
    const s = getComputedStyle(el);
    const halo = parse(s.stroke);
    if (s.paintOrder.startsWith("stroke") && halo && halo.a > 0 && parseFloat(s.strokeWidth) >= 2) {
      return over(halo, htmlBackground(el.ownerSVGElement || el));
    }
    const r = el.getBoundingClientRect();
    const under = document.elementsFromPoint(r.left + r.width / 2, r.top + r.height / 2);
    for (const e of under) {
      if (e === el || e.contains(el) && !(e instanceof SVGGeometryElement)) continue;
      if (e instanceof SVGGeometryElement) {
        const f = parse(getComputedStyle(e).fill);
        if (f && f.a > 0) return over(f, htmlBackground(el.ownerSVGElement || el));
      }
    }
    return htmlBackground(el.ownerSVGElement || el);
  };
  const fade = (el) => {
    let o = 1;
    for (let e = el; e && e.nodeType === 1; e = e.parentElement) o *= parseFloat(getComputedStyle(e).opacity);
    return o;
  };
  const out = [];
  const all = document.querySelectorAll("body *");
  for (const el of all) {
    if (!el.checkVisibility({ opacityProperty: true, visibilityProperty: true })) continue;
    if (["SCRIPT", "STYLE", "OPTION", "TITLE"].includes(el.tagName)) continue;
    const text = [...el.childNodes].filter((n) => n.nodeType === 3).map((n) => n.textContent).join("").trim();
    if (!text) continue;
    if (el.closest("[disabled], [aria-disabled='true']")) continue;  // inactive controls
    const r = el.getBoundingClientRect();
    if (r.width < 1 || r.height < 1) continue;
    const s = getComputedStyle(el);
    const svg = el instanceof SVGElement;
    const bg = svg ? svgBackground(el) : htmlBackground(el);
    let fg = parse(svg ? s.fill : s.color);
    if (!fg) continue;
    fg = over({ ...fg, a: fg.a * fade(el) }, bg);
    const size = parseFloat(s.fontSize), bold = parseInt(s.fontWeight, 10) >= 700;
    const need = size >= 24 || (bold && size >= 18.66) ? 3 : 4.5;
    const got = ratio(fg, bg);
    if (got + 1e-6 < need) {
      const hex = (c) => "#" + [c.r, c.g, c.b].map((v) => Math.round(v).toString(16).padStart(2, "0")).join("");
      out.push({ text: text.slice(0, 40), where: (el.id ? "#" + el.id : el.tagName.toLowerCase()) + (el.className && el.className.baseVal === undefined ? "." + String(el.className).trim().replace(/\s+/g, ".") : ""),
                 ratio: Math.round(got * 100) / 100, need, fg: hex(fg), bg: hex(bg) });
    }
  }
  return out;
}
"""

FIT_JS = r"""
() => {
  const out = [];
  const W = document.documentElement.clientWidth;
  if (document.documentElement.scrollWidth > W + 1) {
    const wide = [...document.querySelectorAll("body *")].filter((e) => e.checkVisibility() && e.getBoundingClientRect().right > W + 1)
      .slice(0, 5).map((e) => (e.id ? "#" + e.id : e.tagName.toLowerCase()) + "." + String(e.className.baseVal ?? e.className).trim().replace(/\s+/g, "."));
    out.push(`the page is ${document.documentElement.scrollWidth} px wide in a ${W} px window: ${wide.join(", ")}`);
  }
  // every button of a command row, mode row and the header: whole, inside its row and the window,
  // its label not cut
  for (const b of document.querySelectorAll(".cmds button, .cell-cmds button, .modes button, .top a, .top button")) {
    if (!b.checkVisibility()) continue;
    const r = b.getBoundingClientRect();
    const row = b.parentElement.getBoundingClientRect();
    const name = b.textContent.trim().slice(0, 30);
    if (r.left < -1 || r.right > W + 1) out.push(`${name}: outside the window (${Math.round(r.left)}..${Math.round(r.right)} of ${W})`);
    if (r.left < row.left - 1 || r.right > row.right + 1 || r.top < row.top - 1 || r.bottom > row.bottom + 1) out.push(`${name}: outside its row`);
    if (b.scrollWidth > b.clientWidth + 1) out.push(`${name}: its label is cut (${b.scrollWidth} > ${b.clientWidth})`);
    for (let e = b.parentElement; e && e !== document.body; e = e.parentElement) {
      const s = getComputedStyle(e);
      if (s.overflowX !== "visible" || s.overflowY !== "visible") {
        const c = e.getBoundingClientRect();
        if (r.right > c.right + 1 || r.bottom > c.bottom + 1 || r.left < c.left - 1 || r.top < c.top - 1) out.push(`${name}: clipped by ${e.tagName.toLowerCase()}.${e.className}`);
        break;
      }
    }
  }
  // the header's items do not overlap one another
  const items = [...document.querySelectorAll(".top .nav a, .top .access > *, .top .conn")].filter((e) => e.checkVisibility())
    .map((e) => [e.textContent.trim().slice(0, 20), e.getBoundingClientRect()]);
  for (let i = 0; i < items.length; i++) {
    for (let j = i + 1; j < items.length; j++) {
      const [a, p] = items[i], [b, q] = items[j];
      if (p.left < q.right - 1 && q.left < p.right - 1 && p.top < q.bottom - 1 && q.top < p.bottom - 1) out.push(`${a} overlaps ${b}`);
    }
  }
  // labels and values are not cut off with hidden overflow
  for (const e of document.querySelectorAll(".banner *, .cell-card *, .unit-card *, .kv *, .fact *")) {
    if (!e.checkVisibility()) continue;
    const s = getComputedStyle(e);
    if (s.overflowX === "hidden" && e.scrollWidth > e.clientWidth + 1) out.push(`${e.textContent.trim().slice(0, 30)}: cut off`);
  }
  return out;
}
"""


def contrast_failures(page: Any) -> list[dict[str, Any]]:
    """Every visible text element under WCAG 2.1 AA contrast on ``page``."""
    failures: list[dict[str, Any]] = page.evaluate(CONTRAST_JS)
    return failures


def fit_failures(page: Any) -> list[str]:
    """What does not fit on ``page``: sideways overflow, a command cut, header items on top of
    one another, labels cut off."""
    failures: list[str] = page.evaluate(FIT_JS)
    return failures
