// The recipe screen of a unit (#/unit/<name>/recipe): its recipes (from the cell file, in the
// configuration), the one chosen compared side by side with the one in use (the parameters that
// differ highlighted), the Change button, the changeover's progress per equipment module (each
// one's answer, and the reason of a refusal) and how the last changeover ended. Whether the unit
// takes a recipe change now is the server's word (the unit's `why`: `recipe`), as for commands.
import { blocked, isLost, ownReasons } from "./access.js";
import { renderFeedback } from "./actions.js";
import { $, button, esc, setButton, view } from "./dom.js";
import { S, ST, conn, unitCfg } from "./store.js";

/** The recipe chosen on this page, per unit (kept across redraws). */
const chosen = {};

const recipesOf = (unit) => unitCfg(unit)?.recipes || [];
const recipeById = (unit, id) => recipesOf(unit).find((r) => r.id === id);

/** "2 · water 1.0" for recipe ``id`` of ``unit`` (``name``: the one the unit sent, if any). */
export function recipeLabel(unit, id, name = "") {
  if (!id) return "none";
  const r = recipeById(unit, id);
  const shown = name || r?.name || "";
  return shown ? `${id} · ${shown}` : String(id);
}

function buildRecipe(name) {
  const el = $("#screen-recipe");
  const recipes = recipesOf(name);
  const options = recipes.map((r) => `<option value="${r.id}">${esc(recipeLabel(name, r.id))}</option>`).join("");
  const home = `#/unit/${encodeURIComponent(name)}`;
  el.innerHTML = `
    <div class="subtabs" role="tablist"><a id="r-tab-unit" role="tab" href="${home}">Operation</a><a id="r-tab-recipe" role="tab" class="active" aria-selected="true" href="${home}/recipe">Recipe</a></div>
    <div class="grid cols-recipe">
      <div class="card"><h2>Recipe <span class="right" id="r-current"></span></h2>
        ${recipes.length
          ? `<div class="recipe-pick"><label for="r-select" class="muted">Change to</label><select id="r-select" aria-label="recipe to change to">${options}</select>${button("Change recipe", "set_recipe", { unit: name, args: {}, cls: "primary", why: "…", attrs: 'id="r-change"' })}</div>`
          : `<div class="empty">no recipes configured for ${esc(name)}</div>`}
        <div class="why-line" id="r-why"></div>
        <div class="feedback" id="r-feedback" data-feedback="${esc(name)}"></div>
        <div class="table-wrap mt-s"><table id="r-compare"><thead><tr><th>Parameter</th><th id="r-col-current">In use</th><th id="r-col-chosen">Chosen</th></tr></thead><tbody></tbody></table></div>
        <div class="muted small mt-xs" id="r-diff-count"></div>
      </div>
      <div class="stack">
        <div class="card"><h2>Changeover <span class="right muted" id="r-order"></span></h2>
          <div class="progress-line" id="r-progress"></div>
          <div class="table-wrap"><table id="r-ems"><thead><tr><th>EM</th><th>Answer</th><th>Reason</th></tr></thead><tbody></tbody></table></div></div>
        <div class="card"><h2>Last result</h2><div class="recipe-result" id="r-result"></div></div>
      </div>
    </div>`;
  const select = $("#r-select");
  if (select) {
    select.addEventListener("change", () => {
      chosen[name] = +select.value;
      renderRecipe();
    });
  }
  S.builtRecipe = name;
}

// -- the comparison ------------------------------------------------------------------------------
function shownValue(p) {
  if (!p) return "–";
  const v = p.type === "string" ? p.text : p.type === "dint" ? String(Math.round(p.value)) : String(p.value);
  return p.unit ? `${v} ${p.unit}` : v;
}

/** key -> [group, name, parameter] of a recipe's rows, in its order. */
function rowsOf(r) {
  const rows = new Map();
  if (!r) return rows;
  rows.set("qty", ["", "primary quantity", { type: "lreal", value: r.primary_qty, unit: r.unit }]);
  for (const p of r.process_variables) rows.set(`pv:${p.id}`, ["Process variables", p.name || `#${p.id}`, p]);
  for (const i of r.ingredients) {
    for (const p of i.parameters) rows.set(`in${i.ingredient_id}:${p.id}`, [`Ingredient ${i.ingredient_id}`, p.name || `#${p.id}`, p]);
  }
  return rows;
}

function compare(current, picked) {
  const a = rowsOf(current), b = rowsOf(picked);
  const keys = [...new Set([...a.keys(), ...b.keys()])];
  let group = null, differ = 0;
  const out = [];
  for (const k of keys) {
    const [g, label] = a.get(k) || b.get(k);
    if (g !== group && g) out.push(`<tr class="group"><td colspan="3">${esc(g)}</td></tr>`);
    group = g;
    const x = shownValue(a.get(k)?.[2]), y = shownValue(b.get(k)?.[2]);
    const diff = !!current && !!picked && x !== y;
    if (diff) differ++;
    out.push(`<tr data-param="${esc(k)}" data-diff="${diff}" class="${diff ? "diff" : ""}"><td>${esc(label)}</td><td>${esc(x)}</td><td>${esc(y)}</td></tr>`);
  }
  return { html: out.join("") || `<tr><td colspan="3" class="empty">no parameters</td></tr>`, differ };
}

// -- the changeover ------------------------------------------------------------------------------
function answerCell(e) {
  const a = e.recipe_answer_name;
  if (a === "pending") return `<span class="lamp on-info blink"></span> pending`;
  if (a === "accepted") return `<span class="tag ok">accepted</span>`;
  if (a === "refused") return `<span class="tag bad">refused</span>`;
  return `<span class="muted">–</span>`;
}

/** Redraw the recipe screen of the unit the address names. */
export function renderRecipe() {
  const name = S.route.unit;
  if (S.builtRecipe !== name || !$("#r-compare")) buildRecipe(name);
  const x = ST.units[name] || {};
  const s = x.status;
  $("#screen-recipe").classList.toggle("stale", isLost(name) || !conn.ok);
  const recipes = recipesOf(name);
  const current = s ? recipeById(name, s.recipe_current) : null;
  if (chosen[name] === undefined || !recipeById(name, chosen[name])) {
    // first: a recipe other than the one in use (the one an operator comes to change to)
    chosen[name] = (recipes.find((r) => r.id !== s?.recipe_current) || recipes[0])?.id;
  }
  const picked = recipeById(name, chosen[name]);
  const select = $("#r-select");
  if (select && document.activeElement !== select) select.value = String(chosen[name]);

  view($("#r-current")).html = s ? `in use <b id="r-current-recipe">${esc(recipeLabel(name, s.recipe_current, s.recipe_current_name))}</b>` : "";
  $("#r-col-current").textContent = `In use${s ? `: ${recipeLabel(name, s.recipe_current, s.recipe_current_name)}` : ""}`;
  $("#r-col-chosen").textContent = `Chosen${picked ? `: ${recipeLabel(name, picked.id)}` : ""}`;
  const cmp = compare(current, picked);
  view($("#r-compare tbody")).html = cmp.html;
  $("#r-diff-count").textContent = current && picked ? (current.id === picked.id ? "the chosen recipe is the one in use" : `${cmp.differ} parameter(s) differ (highlighted)`) : "";

  // the Change button: the page's own reasons (connection, login, level), then the unit's
  const b = $("#r-change");
  if (b) {
    const reasons = ownReasons(x.why || { commands: {}, modes: {}, ems: {} });
    const why = blocked(name, "set_recipe") || reasons.recipe || (picked ? "" : "choose a recipe");
    setButton(b, why);
    b.dataset.args = JSON.stringify(picked ? { recipe_id: picked.id } : {});
    b.dataset.label = picked ? `Recipe ${recipeLabel(name, picked.id)}` : "Recipe";
    b.textContent = picked ? `Change to ${picked.name || picked.id}` : "Change recipe";
    view($("#r-why")).html = why && s ? `<span class="tag warn">not now</span> ${esc(why)}` : "";
  }
  renderFeedback($("#r-feedback"), name);

  // progress: the changeover running, each EM's answer to the last order
  $("#r-order").textContent = s?.recipe_changeover ? `order #${s.recipe_changeover}` : "";
  const ems = (s?.equipment_modules || []).filter((e) => e.active || e.recipe_answer);
  const prog = $("#r-progress");
  if (!s) prog.textContent = "no status from this unit yet";
  else if (s.recipe_change_in_process) {
    const waiting = ems.filter((e) => e.recipe_answer_name === "pending").map((e) => e.name);
    view(prog).html = `<b>Changeover in process</b> → ${esc(recipeLabel(name, s.recipe_requested))}${waiting.length ? ` · waiting for ${esc(waiting.join(", "))}` : ""}`;
  } else prog.textContent = "No changeover running";
  $("#r-progress").dataset.running = String(!!s?.recipe_change_in_process);
  view($("#r-ems tbody")).html = ems.map((e) => `<tr data-em="${esc(e.name)}" data-answer="${esc(e.recipe_answer_name || "none")}"><td><b>${esc(e.name)}</b></td><td>${answerCell(e)}</td><td class="reason">${esc(e.recipe_message || "")}</td></tr>`).join("") || `<tr><td colspan="3" class="empty">no equipment modules</td></tr>`;

  const result = $("#r-result");
  const text = s?.recipe_result || "";
  result.className = `recipe-result${/\brefused\b|\bno answer\b/.test(text) ? " refused" : text ? " applied" : ""}`;
  result.textContent = text || "no changeover since the unit started";
}
