"""A unit's recipe inputs: a recipe change requested (``set_recipe``), an EM's answer to a
changeover order, and the order's timeout (the workflow: :mod:`.recipes`, docs/packml.md §6a).

While a changeover runs (``RecipeChangeInProcess``) the unit refuses state commands other than
Stop and Abort (the ``recipe`` guard, reason RECIPE_CHANGE_IN_PROCESS), mode changes and another
recipe change; Stop and Abort pass, and the changeover runs on to its end (the EMs decide).
"""

from __future__ import annotations

from . import inputlog
from .deadlines import Due
from .machine import UnitMachine
from .numbers import state_name
from .reasons import Answer, Reason
from .recipes import Changeover, EmAnswer, Phase, Recipe, states_text
from .rules import OPERATOR, Watch

#: Characters of an EM's refusal reason the unit keeps.
MAX_REASON = 200


class RecipeInputs(UnitMachine):
    """The recipe inputs of a :class:`~.unit.Unit`; the recipes are :class:`~.recipes.Recipes`'."""

    __slots__ = ()

    def set_recipe(self, recipe_id: int, name: str = "", source: str = OPERATOR) -> Answer:
        """``Command.RecipeChangeRequest`` with ``SelectedRecipe``: by ID (> 0) or by name."""
        source = source or OPERATOR
        with self._input(inputlog.RECIPE, recipe_id, name, source):
            return self._locked("changing the recipe", source) or self._set_recipe(
                int(recipe_id), str(name), source
            )

    def _set_recipe(self, recipe_id: int, name: str, source: str) -> Answer:
        book, unit = self.recipes.book, self.config.name
        recipe = book.find(recipe_id, name)
        if recipe is None:
            asked = f"recipe {recipe_id}" if recipe_id or not name else f"recipe {name[:80]!r}"
            return Answer.no(
                Reason.RECIPE_UNKNOWN, f"{asked} is not one of {unit}'s recipes ({book.listing()})"
            )
        where = f"{state_name(self.state)} ({self.mode_def.name})"
        running = self.recipes.changeover
        if running is not None:
            return Answer.no(
                Reason.RECIPE_CHANGE_IN_PROCESS,
                f"recipe {recipe.label} refused in {where}: the changeover to "
                f"{running.requested.label} is in process",
            )
        if self.mode_change_in_process:
            return Answer.no(
                Reason.MODE_CHANGE_IN_PROCESS,
                f"recipe {recipe.label} refused in {where}: {self.mode_change_text()}",
            )
        if self.state not in book.states:
            return Answer.no(
                Reason.RECIPE_NOT_ALLOWED,
                f"recipe {recipe.label} refused in {where}: {unit} changes its recipe only in "
                f"{states_text(book.states)}",
            )
        ems = [n for n, em in self.equipment.modules.items() if em.active and em.online]
        c = self.recipes.begin(recipe, source, self._t, ems)
        self.alert.set(Watch.RECIPE, True)
        self.alarms.log_event(
            f"recipe change to {recipe.label} requested by {source}", self._t, source=source
        )
        self._log("info", f"changeover to recipe {recipe.label} by {source}: order {c.order}")
        self._send(c)
        if not ems:
            self._end(f"recipe {recipe.label} applied (no EM to ask)", recipe)
            return Answer.ok(f"recipe {recipe.label} applied")
        return Answer.ok(
            f"changeover to recipe {recipe.label} begun: {len(ems)} EM(s) asked "
            f"({', '.join(ems)}); follow recipe_change_in_process"
        )

    def em_recipe(self, name: str, order: int, accepted: bool, reason: str = "") -> Answer:
        """EM ``name`` answers changeover order ``order``: applied, or refused with ``reason``."""
        with self._input(inputlog.EM_RECIPE, name, order, accepted, reason):
            c = self.recipes.changeover
            if c is None or c.order != order or name not in c.answers:
                return Answer.no(Reason.NOTHING_TO_DO, f"no changeover order {order} for {name}")
            if c.answers[name][0] is not EmAnswer.PENDING:
                return Answer.no(Reason.NOTHING_TO_DO, f"{name} already answered order {order}")
            why = " ".join(str(reason).split())[:MAX_REASON] or "no reason given"
            answer = EmAnswer.ACCEPTED if accepted else EmAnswer.REFUSED
            kept = c.answers[name][1] if accepted else why  # (a rollback keeps the refusal's)
            c.answers[name] = (answer, kept)
            self._rev += 1
            if not accepted:
                self._log("warn", f"EM {name} refused recipe {c.sent.label}: {why}")
            self._decide(c)
            return Answer.ok("answer taken")

    def _em_gone_from_changeover(self, name: str, reason: str) -> None:
        c = self.recipes.changeover
        if c is None or c.answers.get(name, (None, ""))[0] is not EmAnswer.PENDING:
            return
        c.answers[name] = (EmAnswer.REFUSED, reason)
        self._rev += 1
        self._log("warn", f"EM {name} {reason} while its answer to {c.sent.label} was awaited")
        self._decide(c)

    def _on_recipe_timeout(self, order: int) -> None:
        c = self.recipes.changeover
        if c is None or c.order != order:
            return
        seconds = self.recipes.book.timeout
        for em in c.pending:
            c.answers[em] = (EmAnswer.REFUSED, f"no answer within {seconds:g} s")
            self._log("warn", f"EM {em} did not answer recipe order {order} within {seconds:g} s")
        self._rev += 1
        self._decide(c)

    def _decide(self, c: Changeover) -> None:
        """Every EM answered (or one refused the apply phase): commit, roll back or end."""
        refused = [(em, why) for em, (a, why) in c.answers.items() if a is EmAnswer.REFUSED]
        if c.phase is Phase.APPLY:
            if refused:
                em, why = refused[0]
                self._send(self.recipes.rollback(f"EM {em} refused it: {why}", self._t))
                modules = self.equipment.modules
                gone = [n for n in c.answers if n not in modules or not modules[n].online]
                for n in gone:  # (a lost EM cannot answer the rollback: its refusal stands)
                    c.answers[n] = (EmAnswer.REFUSED, c.answers[n][1] or "lost")
                if gone:
                    self._decide(c)
                return
            if c.pending:
                return
            seconds = self._t - c.started
            self._end(f"recipe {c.requested.label} applied in {seconds:.1f} s", c.requested)
            return
        if c.pending:
            return
        back = f"rolled back to {c.previous.label}" if c.previous.id else "rolled back"
        if refused:
            names = ", ".join(em for em, _ in refused)
            back += f" (not by {names}: {refused[0][1]})"
        self._end(f"recipe {c.requested.label} refused: {c.refusal}; {back}", c.previous)

    def _send(self, c: Changeover) -> None:
        """The order out now goes to the EMs (the node publishes it on ``recipe``)."""
        self._rev += 1
        self._queue(("recipe", (c.order, int(c.phase), c.sent, tuple(c.answers))))
        if c.answers:
            self._arm(c)

    def _arm(self, c: Changeover) -> None:
        self.deadlines.at(c.deadline, Due.RECIPE_TIMEOUT, c.order)

    def _end(self, result: str, current: Recipe) -> None:
        self.recipes.end(result, current)
        self._rev += 1
        self.alert.set(Watch.RECIPE, False)
        self.alarms.log_event(result[:240], self._t, source="unit")
        self._log("info", result)
