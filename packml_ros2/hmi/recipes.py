"""A unit's recipes for the page (issue 32): the book from the cell file, why a recipe change is
not available now, and the ``set_recipe`` action's arguments.

The recipes come from the unit's configuration (:class:`~packml_ros2.core.recipes.RecipeBook`,
the same the unit loads), the recipe in use and the changeover in progress from its status. Why
the Change button is disabled is judged as the unit judges ``set_recipe`` (core/recipe_inputs.py),
in the same order: the remote lock for the HMI's source, a changeover in process, a mode change in
process, a state the book does not allow. Everything here reads what a unit published, which may
be anything: never an exception.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ..core.config import UnitConfig
from ..core.recipes import MAX_TEXT, EmAnswer
from ..core.rules import LOCKED_SENTENCE, remote_locked
from ..core.schema import shown

INT32_MAX = 2**31 - 1
#: ``recipe_answer`` of an EM (EmSummary.msg's RECIPE_*) as the page names it.
EM_ANSWERS = {int(a): a.name.lower() for a in EmAnswer}


def recipe_config(u: UnitConfig) -> dict[str, Any]:
    """``{recipes: [Recipe.to_dict, by id], recipe_states: [state names], recipe_timeout}``."""
    book = u.recipes
    return {
        "recipes": [book.recipes[i].to_dict() for i in sorted(book.recipes)],
        "recipe_states": [s.name for s in sorted(book.states)],
        "recipe_timeout": book.timeout,
    }


def recipe_reason(config: UnitConfig, status: Mapping[str, Any] | None, source: str) -> str:
    """Why ``config``'s unit would not take a recipe change from ``source`` now ('' = it would;
    also '' without a status: the page says that itself)."""
    name = config.name
    if not config.recipes.recipes:
        return f"{name} has no recipes configured"
    if status is None:
        return ""
    if remote_locked(source, bool(status.get("remote_commands_enabled", True))):
        return LOCKED_SENTENCE.format(what="changing the recipe", source=source, unit=name)
    where = f"{status.get('state_name', '?')} ({status.get('mode_name', '?')})"
    if status.get("recipe_change_in_process"):
        requested = status.get("recipe_requested", 0)
        book = config.recipes.recipes
        label = book[requested].label if requested in book else str(requested)
        return f"not in {where}: the changeover to recipe {label} is in process"
    if status.get("mode_change_in_process"):
        return f"not in {where}: a mode change is in process"
    state = status.get("state")
    allowed = config.recipes.states
    if not any(state == int(s) for s in allowed):
        names = ", ".join(s.name for s in sorted(allowed))
        return f"not in {where}: {name} changes its recipe only in {names}"
    return ""


def set_recipe_args(args: Mapping[str, Any]) -> dict[str, Any]:
    """The request fields of ``set_recipe`` from the page's ``{recipe_id}`` or ``{recipe_name}``
    (exactly one); ValueError with the reason otherwise."""
    extra = sorted(k for k in args if k not in ("recipe_id", "recipe_name"))
    if extra:
        raise ValueError(
            f"unknown argument {shown(extra[0])} (it takes 'recipe_id' or 'recipe_name')"
        )
    if ("recipe_id" in args) == ("recipe_name" in args):
        raise ValueError("give 'recipe_id' (1 or more) or 'recipe_name', one of them")
    if "recipe_id" in args:
        rid = args["recipe_id"]
        if isinstance(rid, bool) or not isinstance(rid, int):
            raise ValueError("'recipe_id' must be an integer")
        if not 1 <= rid <= INT32_MAX:
            raise ValueError(f"'recipe_id' must be 1..{INT32_MAX}, not {shown(rid)}")
        return {"recipe_id": rid, "recipe_name": ""}
    text = args["recipe_name"]
    if not isinstance(text, str) or not text.strip():
        raise ValueError("'recipe_name' must be a non-empty string")
    if len(text) > MAX_TEXT or not text.isprintable():
        raise ValueError(f"'recipe_name' must be at most {MAX_TEXT} printable characters")
    return {"recipe_id": 0, "recipe_name": text}


__all__ = ["EM_ANSWERS", "recipe_config", "recipe_reason", "set_recipe_args"]
