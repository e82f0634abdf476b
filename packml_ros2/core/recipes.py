"""Recipes and the changeover that puts one in use (docs/packml.md §6a).

A recipe (Schneider's ``ST_Recipe``, the OPC 30050 v2 draft's ``PackMLRecipeDataType``) has an
ID, a name, the unit of its primary quantity, the quantity, and typed parameters: process
variables and ingredients, each parameter REAL, LREAL, DINT or STRING. A unit's recipes come from
its cell file (``recipes:``) and a directory of recipe files (``recipe_dir:``), validated like
the rest of the file.

A changeover (``set_recipe``) runs in two phases, each an *order* with its own number:

1. **apply**: every active, online EM is sent the requested recipe and answers (its
   ``on_recipe`` hook ran, or refused with a reason). All accept: the recipe is
   ``RecipeCurrent``.
2. **rollback**, only when one refused (or did not answer within ``recipe_timeout``): every EM
   asked is sent the previous recipe again, so none is left with a recipe the unit does not
   show. The changeover is then refused as a whole, with the EM's reason.

:class:`Recipes` is the unit's part holding the book, the current recipe and the changeover in
progress; the engine's inputs are :mod:`.recipe_inputs`'.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import Any

from . import schema as sc
from .numbers import State, parse_state, state_name
from .safe_yaml import read_document
from .schema import Node, invalid

#: The states a recipe may change in unless the unit says otherwise (``recipe_states``).
DEFAULT_STATES = frozenset({State.STOPPED, State.IDLE, State.COMPLETE})
#: Seconds every EM has to answer an order (``recipe_timeout``).
DEFAULT_TIMEOUT = 60.0
#: The most recipes a unit holds, and recipe files a directory may have.
MAX_RECIPES = 1000
MAX_TEXT = 255  #: characters of a name, unit or STRING value
FLOAT32_MAX = 3.4028234663852886e38
INT32 = (-(2**31), 2**31 - 1)


class ParamType(IntEnum):
    """A parameter's type (RecipeParameter.msg's TYPE_*)."""

    REAL = 0
    LREAL = 1
    DINT = 2
    STRING = 3


class Phase(IntEnum):
    """What an order asks (RecipeOrder.msg's PHASE_*)."""

    NONE = 0
    APPLY = 1
    ROLLBACK = 2


class EmAnswer(IntEnum):
    """An EM's answer to the last order (EmSummary.msg's RECIPE_*)."""

    NONE = 0
    PENDING = 1
    ACCEPTED = 2
    REFUSED = 3


@dataclass(frozen=True)
class Param:
    """A typed parameter: ``value`` for numbers, ``text`` for STRING."""

    id: int
    name: str = ""
    unit: str = ""
    type: ParamType = ParamType.REAL
    value: float = 0.0
    text: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "name": self.name,
            "unit": self.unit,
            "type": self.type.name.lower(),
            "value": self.value,
            "text": self.text,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Param:
        return cls(
            int(d["id"]),
            str(d.get("name", "")),
            str(d.get("unit", "")),
            ParamType[str(d.get("type", "real")).upper()],
            float(d.get("value", 0.0)),
            str(d.get("text", "")),
        )


@dataclass(frozen=True)
class RecipeIngredient:
    ingredient_id: int
    parameters: tuple[Param, ...] = ()


@dataclass(frozen=True)
class Recipe:
    """One recipe. ID 0 is "no recipe" (a unit before its first changeover)."""

    id: int
    name: str = ""
    unit: str = ""
    primary_qty: float = 0.0
    process_variables: tuple[Param, ...] = ()
    ingredients: tuple[RecipeIngredient, ...] = ()

    def parameter(self, name: str, ingredient: int | None = None) -> float | int | str:
        """The value of the process variable (or of ``ingredient``'s parameter) ``name``: a
        float (REAL, LREAL), an int (DINT) or the text of a STRING; KeyError when there is
        none."""
        if ingredient is None:
            params = self.process_variables
        else:
            found = [i for i in self.ingredients if i.ingredient_id == ingredient]
            params = found[0].parameters if found else ()
        for p in params:
            if p.name == name:
                if p.type is ParamType.DINT:
                    return int(p.value)
                return p.text if p.type is ParamType.STRING else p.value
        raise KeyError(f"recipe {self.label} has no parameter {name!r}")

    @property
    def label(self) -> str:
        return f"{self.id} {self.name!r}" if self.name else str(self.id)

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "name": self.name,
            "unit": self.unit,
            "primary_qty": self.primary_qty,
            "process_variables": [p.to_dict() for p in self.process_variables],
            "ingredients": [
                {
                    "ingredient_id": i.ingredient_id,
                    "parameters": [p.to_dict() for p in i.parameters],
                }
                for i in self.ingredients
            ],
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Recipe:
        return cls(
            int(d["id"]),
            str(d.get("name", "")),
            str(d.get("unit", "")),
            float(d.get("primary_qty", 0.0)),
            tuple(Param.from_dict(p) for p in d.get("process_variables", [])),
            tuple(
                RecipeIngredient(
                    int(i["ingredient_id"]),
                    tuple(Param.from_dict(p) for p in i.get("parameters", [])),
                )
                for i in d.get("ingredients", [])
            ),
        )


NO_RECIPE = Recipe(0)


@dataclass(frozen=True)
class RecipeBook:
    """A unit's recipes and the rules of changing them (the cell file's ``recipe*`` keys)."""

    recipes: Mapping[int, Recipe] = field(default_factory=dict)
    states: frozenset[State] = DEFAULT_STATES
    timeout: float = DEFAULT_TIMEOUT
    initial: int = 0  #: RecipeCurrent of a unit that has none stored

    def find(self, recipe_id: int, name: str = "") -> Recipe | None:
        if recipe_id:
            return self.recipes.get(recipe_id)
        key = name.strip().casefold()
        return next((r for r in self.recipes.values() if r.name.casefold() == key), None)

    def listing(self, limit: int = 8) -> str:
        shown = [r.label for r in list(self.recipes.values())[:limit]]
        more = len(self.recipes) - len(shown)
        return ", ".join(shown) + (f" and {more} more" if more > 0 else "") or "none"


# -- configuration ---------------------------------------------------------------------------------
_TYPES = {t.name.lower(): t for t in ParamType}
_PARAM_KEYS = {"id", "name", "unit", "type", "value", "min", "max"}


def _config_param(p: Param) -> dict[str, Any]:
    value: Any = p.text if p.type is ParamType.STRING else p.value
    if p.type is ParamType.DINT:
        value = int(p.value)
    return {"id": p.id, "name": p.name, "unit": p.unit, "type": p.type.name.lower(), "value": value}


def recipe_config(r: Recipe) -> dict[str, Any]:
    """A recipe as a ``recipes:`` entry of a cell file."""
    return {
        "id": r.id,
        "name": r.name,
        "unit": r.unit,
        "primary_qty": r.primary_qty,
        "process_variables": [_config_param(p) for p in r.process_variables],
        "ingredients": [
            {
                "ingredient_id": i.ingredient_id,
                "parameters": [_config_param(p) for p in i.parameters],
            }
            for i in r.ingredients
        ],
    }


def inline_recipes(document: Any, unit: str, book: RecipeBook) -> Any:
    """The cell file ``document`` with unit ``unit``'s recipes written in it (those of its
    ``recipe_dir`` too, which is dropped): what the unit publishes on ``~/config`` and a
    recording keeps, so the unit replays on a machine without that directory."""
    units = document.get("units") if isinstance(document, dict) else None
    entry = units.get(unit) if isinstance(units, dict) else None
    defaults = document.get("defaults") if isinstance(document, dict) else None
    had_dir = isinstance(entry, dict) and "recipe_dir" in entry
    had_dir |= isinstance(defaults, dict) and "recipe_dir" in defaults
    if not had_dir or not isinstance(entry, dict):
        return document
    entry.pop("recipe_dir", None)
    if isinstance(defaults, dict):
        defaults.pop("recipe_dir", None)
    entry["recipes"] = [recipe_config(r) for r in book.recipes.values()]
    return document


_RECIPE_KEYS = {"id", "name", "unit", "primary_qty", "process_variables", "ingredients"}


def _text(n: Node) -> str:
    value = sc.text(n)
    if len(value) > MAX_TEXT:
        raise invalid(f"{len(value)} characters; at most {MAX_TEXT}")
    return value


def _param(n: Node) -> Param:
    n.check_keys(_PARAM_KEYS)
    m = n.mapping()
    ptype = n.get("type", sc.choice(_TYPES), ParamType.REAL)
    pid = n.get("id", sc.integer(*INT32), 0)
    if "id" not in m:
        n.error("a parameter needs an id")
    name, unit = n.get("name", _text, ""), n.get("unit", _text, "")
    if ptype is ParamType.STRING:
        if "min" in m or "max" in m:
            n.error("a STRING parameter has no min or max")
        return Param(pid, name, unit, ptype, 0.0, n.get("value", _text, ""))
    parse: Callable[[Node], float]
    if ptype is ParamType.DINT:
        parse = sc.integer(*INT32)
    else:
        limit = FLOAT32_MAX if ptype is ParamType.REAL else None
        parse = sc.number(lo=-limit if limit else None, hi=limit)
    value = float(n.get("value", parse, 0.0))
    lo, hi = n.get("min", parse, None), n.get("max", parse, None)
    if lo is not None and hi is not None and lo > hi:
        n.error(f"min {lo:g} is above max {hi:g}")
    elif (lo is not None and value < lo) or (hi is not None and value > hi):
        n.child("value", None).error(
            f"{value:g} is outside [{lo if lo is not None else '-inf'}, "
            f"{hi if hi is not None else 'inf'}]"
        )
    return Param(pid, name, unit, ptype, value)


def _params(n: Node, capacity: int) -> tuple[Param, ...]:
    items = tuple(e.parse(_param, Param(0)) for e in n.elements())
    if len(items) > capacity:
        n.error(f"{len(items)} entries, but the array holds {capacity} (sizes)")
    ids = [p.id for p in items]
    for dup in sorted({i for i in ids if ids.count(i) > 1}):
        n.error(f"parameter id {dup} is used twice")
    return items


def _recipe(sizes: Any) -> Any:
    def parse(n: Node) -> Recipe:
        n.check_keys(_RECIPE_KEYS)
        m = n.mapping()
        if "id" not in m:
            n.error("a recipe needs an id (1 or more)")
        ingredients = []
        for e in n.list_at("ingredients"):
            e.check_keys({"ingredient_id", "parameters"})
            ingredients.append(
                RecipeIngredient(
                    e.get("ingredient_id", sc.integer(*INT32), 0),
                    e.get("parameters", lambda x: _params(x, sizes.ingredient_parameters), ()),
                )
            )
        if len(ingredients) > sizes.ingredients:
            n.child("ingredients", None).error(
                f"{len(ingredients)} entries, the array holds {sizes.ingredients}"
            )
        return Recipe(
            n.get("id", sc.integer(1, INT32[1]), 0),
            n.get("name", _text, ""),
            n.get("unit", _text, ""),
            n.get("primary_qty", sc.number(lo=0), 0.0),
            n.get("process_variables", lambda x: _params(x, sizes.process_variables), ()),
            tuple(ingredients),
        )

    return parse


def _recipe_files(n: Node, base_dir: Path) -> list[Node]:
    """The recipe files of directory ``n`` (``*.yaml``, ``*.yml``), sorted, as nodes."""
    path = Path(os.path.expanduser(sc.text(n)))
    if not path.is_absolute():
        path = base_dir / path
    try:
        files = sorted(p for p in path.iterdir() if p.suffix in (".yaml", ".yml"))
    except OSError as exc:
        raise invalid(f"cannot read the directory: {exc.strerror or exc}") from None
    if len(files) > MAX_RECIPES:
        raise invalid(f"{len(files)} recipe files; at most {MAX_RECIPES}")
    out = []
    for f in files:
        node = Node(None, f"{n.path}/{f.name}", n.problems)
        try:
            node.value = read_document(f)
        except (OSError, ValueError) as exc:
            node.error(f"cannot read: {str(exc)[:200]}")
            continue
        out.append(node)
    return out


def recipe_book(n: Node, sizes: Any, base_dir: Path) -> RecipeBook:
    """The recipes of unit node ``n`` (keys ``recipes``, ``recipe_dir``, ``recipe_states``,
    ``recipe_timeout``, ``initial_recipe``); problems go to ``n``'s list."""
    nodes = n.list_at("recipes")
    m = n.mapping()
    if "recipe_dir" in m:
        d = n.child("recipe_dir", m["recipe_dir"])
        nodes += d.parse(lambda x: _recipe_files(x, base_dir), [])
    recipes: dict[int, Recipe] = {}
    names: dict[str, int] = {}
    for e in nodes:
        r = e.parse(_recipe(sizes), None)
        if r is None or not r.id:
            continue
        if r.id in recipes:
            e.error(f"recipe id {r.id} is defined twice")
            continue
        key = r.name.casefold()
        if key and key in names:
            e.error(f"recipe name {r.name!r} is also recipe {names[key]}'s")
            continue
        recipes[r.id] = r
        names[key] = r.id
    if len(recipes) > MAX_RECIPES:
        n.child("recipes", None).error(f"{len(recipes)} recipes; at most {MAX_RECIPES}")

    def states(x: Node) -> frozenset[State]:
        found = set()
        for e in x.elements():
            s = e.parse(lambda y: parse_state(sc.text(y)), None)
            if s is not None:
                found.add(s)
        if not found:
            raise invalid("at least one state (e.g. [Stopped, Idle, Complete])")
        return frozenset(found)

    initial = n.get("initial_recipe", sc.integer(0, INT32[1]), 0)
    if initial and initial not in recipes:
        n.child("initial_recipe", None).error(f"no recipe {initial} in recipes")
    return RecipeBook(
        recipes,
        n.get("recipe_states", states, DEFAULT_STATES),
        n.get("recipe_timeout", sc.number(positive=True), DEFAULT_TIMEOUT),
        initial,
    )


RECIPE_KEYS = {"recipes", "recipe_dir", "recipe_states", "recipe_timeout", "initial_recipe"}


# -- the changeover --------------------------------------------------------------------------------
@dataclass
class Changeover:
    """The changeover in progress: the order out now and who answered it."""

    requested: Recipe
    previous: Recipe
    source: str
    started: float
    order: int
    phase: Phase
    deadline: float
    answers: dict[str, tuple[EmAnswer, str]] = field(default_factory=dict)
    refusal: str = ""  #: why the apply phase failed (set when the rollback begins)

    @property
    def sent(self) -> Recipe:
        """The recipe of the order out now."""
        return self.requested if self.phase is Phase.APPLY else self.previous

    @property
    def pending(self) -> list[str]:
        return [em for em, (a, _) in self.answers.items() if a is EmAnswer.PENDING]


class Recipes:
    """The unit's recipe part: its book, ``RecipeCurrent``, the changeover and the last result."""

    __slots__ = ("book", "changeover", "current", "last_answers", "order", "result")

    def __init__(self, book: RecipeBook) -> None:
        self.book = book
        self.current: Recipe = book.recipes.get(book.initial, NO_RECIPE)
        self.changeover: Changeover | None = None
        self.order = 0  #: the number of the last order sent
        self.result = ""  #: how the last changeover ended
        #: each EM's answer to the last order of the last changeover (status)
        self.last_answers: dict[str, tuple[EmAnswer, str]] = {}

    @property
    def requested(self) -> int:
        c = self.changeover
        return c.requested.id if c is not None else 0

    @property
    def in_process(self) -> bool:
        return self.changeover is not None

    def answers(self) -> Mapping[str, tuple[EmAnswer, str]]:
        c = self.changeover
        return c.answers if c is not None else self.last_answers

    def begin(self, recipe: Recipe, source: str, now: float, ems: Iterable[str]) -> Changeover:
        self.order += 1
        c = self.changeover = Changeover(
            recipe,
            self.current,
            source,
            now,
            self.order,
            Phase.APPLY,
            now + self.book.timeout,
            dict.fromkeys(ems, (EmAnswer.PENDING, "")),
        )
        return c

    def shift(self, offset: float) -> None:
        """The clock stepped by ``offset``: a running changeover keeps its time to its timeout."""
        if self.changeover is not None:
            self.changeover.deadline += offset
            self.changeover.started += offset

    def rollback(self, refusal: str, now: float) -> Changeover:
        c = self.changeover
        assert c is not None
        self.order += 1
        c.order, c.phase, c.refusal = self.order, Phase.ROLLBACK, refusal
        c.deadline = now + self.book.timeout
        # (a refusal's reason stays beside its EM while the rollback runs)
        c.answers = {em: (EmAnswer.PENDING, why) for em, (_, why) in c.answers.items()}
        return c

    def end(self, result: str, current: Recipe) -> None:
        """The changeover ended: each EM's answer stays shown (after a rollback: the refusal's
        reason beside the EM that gave it)."""
        c = self.changeover
        self.last_answers = {}
        if c is not None:
            self.last_answers = {
                em: (EmAnswer.REFUSED if why and c.phase is Phase.ROLLBACK else a, why)
                for em, (a, why) in c.answers.items()
            }
        self.changeover = None
        self.current = current
        self.result = result

    def restore_current(self, recipe_id: int) -> str:
        """Take ``recipe_id`` as RecipeCurrent (a restart): '' or why it cannot be."""
        if recipe_id == 0:
            self.current = NO_RECIPE
            return ""
        recipe = self.book.recipes.get(recipe_id)
        if recipe is None:
            return f"the stored RecipeCurrent {recipe_id} is no longer configured; none is current"
        self.current = recipe
        return ""

    # -- snapshot (core/snapshot.py) ----------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        c = self.changeover
        answers = {em: [int(a), m] for em, (a, m) in self.last_answers.items()}
        return {
            "current": self.current.to_dict(),
            "order": self.order,
            "result": self.result,
            "last_answers": answers,
            "changeover": None
            if c is None
            else {
                "requested": c.requested.to_dict(),
                "previous": c.previous.to_dict(),
                "source": c.source,
                "started": c.started,
                "order": c.order,
                "phase": int(c.phase),
                "deadline": c.deadline,
                "refusal": c.refusal,
                "answers": {em: [int(a), m] for em, (a, m) in c.answers.items()},
            },
        }

    def restore(self, d: Mapping[str, Any]) -> None:
        def answers(x: Mapping[str, Any]) -> dict[str, tuple[EmAnswer, str]]:
            return {str(em): (EmAnswer(int(a)), str(m)) for em, (a, m) in x.items()}

        self.current = Recipe.from_dict(d["current"])
        self.order, self.result = int(d["order"]), str(d["result"])
        self.last_answers = answers(d.get("last_answers", {}))
        c = d.get("changeover")
        self.changeover = (
            None
            if c is None
            else Changeover(
                Recipe.from_dict(c["requested"]),
                Recipe.from_dict(c["previous"]),
                str(c["source"]),
                float(c["started"]),
                int(c["order"]),
                Phase(int(c["phase"])),
                float(c["deadline"]),
                answers(c["answers"]),
                str(c.get("refusal", "")),
            )
        )


def states_text(states: Iterable[State]) -> str:
    return ", ".join(state_name(s) for s in sorted(states))


__all__ = [
    "DEFAULT_STATES",
    "DEFAULT_TIMEOUT",
    "NO_RECIPE",
    "RECIPE_KEYS",
    "Changeover",
    "EmAnswer",
    "Param",
    "ParamType",
    "Phase",
    "Recipe",
    "RecipeBook",
    "RecipeIngredient",
    "Recipes",
    "recipe_book",
    "states_text",
]
