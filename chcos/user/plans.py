"""plans - several plans for one goal, tried in turn against a task's world model (thesis 5.4).

:class:`Plans` runs the first permissible :class:`Plan`; when it fails (a ChcosError) the next
permissible one, recording each outcome in the model's command structure and, if given, in an
:class:`~chcos.user.knowledge.Experience` that then orders the plans by how well they worked in
earlier runs. :class:`PlansExhausted` names every failure.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from chcos.errors import ChcosError, Preempted
from chcos.user.knowledge import Experience
from chcos.user.worldmodel import WorldModel


# ---- plans ----------------------------------------------------------------------------------
@dataclass
class Plan:
    """One way of reaching a goal: ``run(*args)`` is awaited and returns the result (or raises
    ChcosError on failure); ``permissible(model)`` says whether the world model allows it now
    (default: always)."""

    name: str
    run: Callable[..., Awaitable[Any]]
    permissible: Callable[[WorldModel], bool] | None = None


class PlansExhausted(ChcosError):
    """Every permissible plan for a goal failed (or none was permissible); the message names
    each plan and why it failed."""


@dataclass
class Plans:
    """Several plans for one ``goal`` (thesis 5.4: "consult the world model to see if another
    sequence of commands is permissible"). :meth:`attempt` runs the first permissible plan,
    and on failure the next permissible one, recording each outcome in the model's command
    structure (``plans``) and, if given, in ``experience`` (pattern = the goal) - which then
    orders the plans by how well they worked in earlier runs."""

    goal: str
    plans: list[Plan]
    experience: Experience | None = None
    failures: list[tuple[str, str]] = field(default_factory=list)

    def order(self) -> list[Plan]:
        """The plans in the order they will be tried."""
        if self.experience is None:
            return list(self.plans)
        names = self.experience.propose(self.goal, [p.name for p in self.plans])
        by = {p.name: p for p in self.plans}
        return [by[n] for n in names]

    def next(self, model: WorldModel, tried: Iterable[str] = ()) -> Plan | None:
        """The next permissible plan not in ``tried`` (None if there is none)."""
        done = set(tried)
        for p in self.order():
            if p.name not in done and (p.permissible is None or p.permissible(model)):
                return p
        return None

    async def attempt(self, model: WorldModel, *args: Any) -> tuple[str, Any]:
        """Try the plans until one succeeds; returns (plan name, result). Preemption is never
        taken for a failure (it propagates). Raises PlansExhausted naming every failure."""
        self.failures = []
        tried: list[str] = []
        log = model.command.setdefault("plans", [])
        while True:
            plan = self.next(model, tried)
            if plan is None:
                why = "; ".join(f"{n}: {e}" for n, e in self.failures) or \
                    "no plan is permissible"
                raise PlansExhausted(f"{self.goal}: every plan failed ({why})")
            tried.append(plan.name)
            model.command["plan"] = plan.name
            try:
                result = await plan.run(*args)
            except Preempted:
                raise
            except ChcosError as exc:
                self.failures.append((plan.name, str(exc)))
                log.append({"goal": self.goal, "plan": plan.name, "ok": False,
                            "error": str(exc)})
                if self.experience is not None:
                    self.experience.record(self.goal, plan.name, False)
                continue
            log.append({"goal": self.goal, "plan": plan.name, "ok": True})
            if self.experience is not None:
                self.experience.record(self.goal, plan.name, True)
            return plan.name, result
