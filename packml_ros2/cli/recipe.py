"""``packml recipe``: a unit's recipes, and a changeover to one of them.

    packml recipe filler                 # the recipes, the current one marked, the last result
    packml recipe filler --show 2        # recipe 2 beside the current one, differences marked
    packml recipe filler 2               # change over to recipe 2 (or by name), following each EM

A changeover prints each EM's answer as it comes and ends with the unit's result: exit 0 when
the recipe is in use, 1 when refused (by the unit, or by an EM: then rolled back), 3 when the
unit does not answer.
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from functools import partial
from typing import Any

from std_msgs.msg import String

from ..client import Unavailable, UnitProxy
from ..core.config import parse_cell
from ..core.recipes import EmAnswer, Param, Recipe, RecipeBook
from ..core.safe_yaml import parse_document
from ..core.schema import ConfigError
from ..ros import interface
from .main import EXIT_OK, EXIT_REFUSED, EXIT_UNAVAILABLE, EXIT_USAGE
from .session import Session, add_common, fail, session

ANSWER = {
    EmAnswer.NONE: "-",
    EmAnswer.PENDING: "pending",
    EmAnswer.ACCEPTED: "accepted",
    EmAnswer.REFUSED: "refused",
}


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "recipe",
        help="list a unit's recipes or change over to one",
        description="Without RECIPE: the unit's recipes (from its configuration), the current one "
        "marked with *, and how the last changeover ended. With RECIPE (an ID or a name): change "
        "over to it; every active EM applies it, and a refusal by one rolls every EM back. Exit 0 "
        "when the recipe is in use, 1 when refused, 3 when the unit does not answer.",
    )
    p.add_argument("unit", help="a unit (name or cell/unit)")
    p.add_argument("recipe", nargs="?", help="the recipe to change over to: ID or name")
    p.add_argument("--show", metavar="RECIPE", help="print a recipe beside the current one")
    p.add_argument("--no-wait", action="store_true", help="answer as soon as the unit accepted")
    p.add_argument(
        "--wait-timeout",
        type=float,
        default=300.0,
        help="seconds to wait for the changeover to end (default 300)",
    )
    p.add_argument("--source", default="operator", help="who asks (default: operator)")
    add_common(p)
    p.set_defaults(func=recipe)


def _book(s: Session, unit: UnitProxy) -> RecipeBook:
    """The unit's recipes, from the configuration it publishes (latched ``~/config``)."""
    topic = interface.TOPIC["config"]
    got: list[str] = []
    done = threading.Event()

    def take(msg: String) -> None:
        got.append(msg.data)
        done.set()

    sub = s.node.create_subscription(String, topic.path(unit.path), take, topic.qos)
    try:
        if not done.wait(s.timeout):
            raise Unavailable(f"{unit.path} published no configuration within {s.timeout:g} s")
    finally:
        s.node.destroy_subscription(sub)
    data = json.loads(got[0])
    cell = parse_cell(parse_document(data["cell_yaml"], f"{unit.path}/config"))
    return cell.units[str(data["unit"])].recipes


def _value(p: Param) -> str:
    shown = p.text if p.type.name == "STRING" else f"{p.value:g}"
    return f"{shown} {p.unit}".strip()


def _params(r: Recipe) -> dict[str, str]:
    out = {f"{p.name or p.id}": _value(p) for p in r.process_variables}
    for i in r.ingredients:
        out.update(
            {f"ingredient {i.ingredient_id} {p.name or p.id}": _value(p) for p in i.parameters}
        )
    out["primary_qty"] = f"{r.primary_qty:g} {r.unit}".strip()
    return out


def _find(book: RecipeBook, text: str) -> Recipe | None:
    return book.find(int(text)) if text.isdigit() else book.find(0, text)


def _list(book: RecipeBook, status: Any) -> int:
    for r in book.recipes.values():
        mark = "*" if r.id == status.recipe_current else " "
        print(f"{mark} {r.id:>4}  {r.name or '-':<24} {r.primary_qty:g} {r.unit}".rstrip())
    if not book.recipes:
        print("no recipes configured")
    states = ", ".join(s.name for s in sorted(book.states))
    print(f"current: {status.recipe_current} {status.recipe_current_name}; changes in {states}")
    if status.recipe_change_in_process:
        print(f"changeover to {status.recipe_requested} in process")
    if status.recipe_result:
        print(f"last changeover: {status.recipe_result}")
    return EXIT_OK


def _show(book: RecipeBook, status: Any, text: str) -> int:
    r = _find(book, text)
    if r is None:
        return fail(f"no recipe {text!r} (recipes: {book.listing()})", EXIT_USAGE)
    current = book.recipes.get(status.recipe_current)
    now = _params(current) if current is not None else {}
    new = _params(r)
    head = current.label if current is not None else "none"
    print(f"  {'parameter':<28} {'current: ' + head:<24} {r.label}")
    for name in dict.fromkeys([*now, *new]):
        a, b = now.get(name, "-"), new.get(name, "-")
        print(f"{'*' if a != b else ' '} {name:<28} {a:<24} {b}")
    return EXIT_OK


def _newer(seen: Any, status: Any) -> bool:
    return status is not seen


def _follow(unit: UnitProxy, order_before: int, timeout: float) -> int:
    """Print each EM's answer as it changes until the changeover ends; its result decides."""
    shown: dict[str, int] = {}
    t0 = time.monotonic()
    deadline = t0 + timeout
    while True:
        status = unit.wait_status(timeout=max(0.0, deadline - time.monotonic()))
        for em in status.equipment_modules:
            if em.recipe_answer and shown.get(em.name) != em.recipe_answer:
                shown[em.name] = em.recipe_answer
                why = f": {em.recipe_message}" if em.recipe_message else ""
                took = time.monotonic() - t0
                print(
                    f"  {em.name}: {ANSWER[EmAnswer(em.recipe_answer)]}{why} ({took:.2f} s)",
                    flush=True,
                )
        if status.recipe_changeover > order_before and not status.recipe_change_in_process:
            print(status.recipe_result)
            return EXIT_REFUSED if " refused: " in status.recipe_result else EXIT_OK
        if time.monotonic() >= deadline:
            raise Unavailable(f"the changeover did not end within {timeout:g} s")
        unit.wait_status(partial(_newer, status), timeout=max(0.0, deadline - time.monotonic()))


def recipe(args: argparse.Namespace) -> int:
    with session(args, topics=("status",)) as s:
        try:
            unit = s.unit(args.unit)
            status = unit.wait_status(timeout=s.timeout)
            if args.recipe is None:
                book = _book(s, unit)
                return _show(book, status, args.show) if args.show else _list(book, status)
            text = args.recipe.strip()
            fields: dict[str, Any] = (
                {"recipe_id": int(text)} if text.isdigit() else {"recipe_name": text}
            )
            before = status.recipe_changeover
            resp = unit.call_sync("set_recipe", s.timeout, source=args.source, **fields)
            print(resp.message, flush=True)
            if not resp.accepted:
                return EXIT_REFUSED
            if args.no_wait:
                return EXIT_OK
            return _follow(unit, before, args.wait_timeout)
        except (LookupError, ConfigError, ValueError) as exc:
            return fail(str(exc), EXIT_USAGE)
        except Unavailable as exc:
            return fail(str(exc), EXIT_UNAVAILABLE)
