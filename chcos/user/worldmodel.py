"""worldmodel - each task's own small world model (thesis 3.5, 4.5, 5.4, 7).

Two data structures, as the thesis asks: a *sensory* one (processed sensory information the task
has seen) and a *command* one (what the task is executing). The owning task writes both directly;
another task may only *ask*, through a query on a link between the two (``ctx.ask``), which the
owning task's model answers with :meth:`WorldModel.answer`. Subclass it to give more context.

On top of the two structures the facility gives what section 7 asks of a world model:

* **context** - every model answers ``doing`` (what its task is executing); :func:`context`
  asks the task that commands the caller, along the command link;
* **prediction** - :meth:`WorldModel.predict` records what a sensory quantity should be (other
  tasks may ask ``predict``), :meth:`WorldModel.compare` compares what arrived with it and gives
  the error vector of section 3.5 (:class:`ErrorVector`);
* **recognizers and learned responses** - :mod:`chcos.user.knowledge` (:class:`Recognizer`,
  :class:`LearnedPattern`, :class:`Experience`, persisted in a :class:`Store`);
* **plans** - :mod:`chcos.user.plans` (:class:`Plans`: when one plan fails the model picks the
  next permissible one).
"""

from __future__ import annotations

import math
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

from chcos.errors import ConfigError, MessageError
from chcos.helpers import is_number

DOING = "doing"
"""The query topic every :class:`WorldModel` answers with what its task is doing (a copy of its
command structure), so a lower task can ask its commander for context."""

PREDICT = "predict"
"""The query topic (with the quantity's name as argument) answered with the current prediction."""

Value = float | Sequence[float] | Mapping[str, float]
"""A sensory quantity: a number, a vector or named numbers."""


class Asker(Protocol):
    """What :func:`context` needs of a task's context (a :class:`chcos.user.context.TaskContext`):
    the name of the task commanding it, and a world-model query along a link."""

    @property
    def commander(self) -> str | None: ...

    def ask(self, peer: str, topic: str, *args: Any,
            timeout: float | None = None) -> Awaitable[Any]: ...


@dataclass(frozen=True)
class Prediction:
    """What a task expects sensory quantity ``topic`` to be: ``expected`` and the error norm
    ``tolerance`` within which an observation is unsurprising, made at time ``t``."""

    topic: str
    expected: Value
    tolerance: float
    t: float


@dataclass(frozen=True)
class ErrorVector:
    """A prediction compared with what arrived (thesis 3.5): ``error`` is observed minus
    expected per component (``""`` for a number, ``"0"``, ``"1"``... for a vector, the names of
    a mapping), ``norm`` its Euclidean length, ``surprise`` true when the norm exceeds the
    prediction's tolerance."""

    topic: str
    expected: Value
    observed: Value
    error: dict[str, float]
    norm: float
    surprise: bool
    t: float


def components(v: Value, what: str = "value") -> dict[str, float]:
    """``v`` as named numbers. Raises ConfigError (naming ``what``) for anything else."""
    try:
        if isinstance(v, Mapping):
            return {str(k): float(x) for k, x in v.items()}
        if is_number(v):
            return {"": float(v)}
        if isinstance(v, Sequence) and not isinstance(v, str):
            return {str(i): float(x) for i, x in enumerate(v)}
    except (TypeError, ValueError):
        pass
    raise ConfigError(f"world model: {what} {v!r} is not a number, a vector or named numbers")


class WorldModel:
    """A task's world model: ``sensory`` and ``command`` dictionaries, predictions with their
    error vectors, and a query interface."""

    def __init__(self) -> None:
        self.sensory: dict[str, Any] = {}
        self.command: dict[str, Any] = {}
        self.predictions: dict[str, Prediction] = {}
        self.errors: dict[str, ErrorVector] = {}
        self.surprises: dict[str, int] = {}

    def answer(self, topic: str, *args: Any) -> Any:
        """Answer another task's query about ``topic``.

        ``doing`` gives a copy of the command structure (what the task is doing); ``predict``,
        NAME the current prediction of NAME; any other topic is looked up in the sensory, then
        the command structure. A subclass may compute context or predictions. Raises
        MessageError if the model knows nothing about it."""
        if topic == DOING:
            return dict(self.command)
        if topic == PREDICT and args:
            p = self.predictions.get(str(args[0]))
            if p is None:
                raise MessageError(f"world model predicts nothing about {args[0]!r}")
            return p.expected
        if topic in self.sensory:
            return self.sensory[topic]
        if topic in self.command:
            return self.command[topic]
        raise MessageError(f"world model has nothing on {topic!r}")

    def predict(self, topic: str, expected: Value, tolerance: float = 0.0,
                t: float = 0.0) -> Prediction:
        """Record the prediction of sensory quantity ``topic`` (a first-class output: the
        sensory part compares arrivals with it, other tasks may ask ``predict``, ``topic``).
        Raises ConfigError for a value that is not numeric or a negative tolerance."""
        components(expected, f"prediction of {topic!r}")
        if not (math.isfinite(tolerance) and tolerance >= 0.0):
            raise ConfigError(f"world model: tolerance {tolerance!r} of {topic!r}: expected a "
                              f"number >= 0")
        p = Prediction(topic, expected, float(tolerance), float(t))
        self.predictions[topic] = p
        return p

    def compare(self, topic: str, observed: Value, t: float = 0.0) -> ErrorVector | None:
        """Compare what arrived for ``topic`` with its prediction; None if nothing is predicted.
        The error vector is kept in ``errors[topic]``; a surprise is counted in
        ``surprises[topic]``. Raises ConfigError if the observation's components differ from
        the prediction's."""
        p = self.predictions.get(topic)
        if p is None:
            return None
        exp = components(p.expected, f"prediction of {topic!r}")
        obs = components(observed, f"observation of {topic!r}")
        if set(exp) != set(obs):
            raise ConfigError(f"world model: the observation of {topic!r} has components "
                              f"{sorted(obs)}, the prediction {sorted(exp)}")
        err = {k: obs[k] - exp[k] for k in exp}
        norm = math.sqrt(sum(e * e for e in err.values()))
        ev = ErrorVector(topic, p.expected, observed, err, norm, norm > p.tolerance, float(t))
        self.errors[topic] = ev
        if ev.surprise:
            self.surprises[topic] = self.surprises.get(topic, 0) + 1
        return ev

    def snapshot(self) -> dict[str, dict[str, Any]]:
        """A shallow copy of both structures (for maps and viewers)."""
        return {"sensory": dict(self.sensory), "command": dict(self.command)}


async def context(ctx: Asker, topic: str = DOING, *args: Any,
                  timeout: float | None = None) -> Any:
    """Ask the task that commands ``ctx``'s task (its current owner) about ``topic`` - by
    default what it is doing - along the command link. None when no task owns this one (idle,
    or invoked from the host). Raises MessageError as :meth:`TaskContext.ask` does (no answer,
    the commander's satellite down); ReadTimeout after ``timeout``."""
    owner = ctx.commander
    if owner is None:
        return None
    return await ctx.ask(owner, topic, *args, timeout=timeout)


_Func = TypeVar("_Func", bound=Callable[..., Awaitable[Any]])


def task(*, world_model: Callable[[], WorldModel]) -> Callable[[_Func], _Func]:
    """Decorate a task's ``async def main(ctx, command)`` with the class (or factory) of the
    world model its task gets at install (without it: a plain :class:`WorldModel`)::

        @task(world_model=GapModel)
        async def main(ctx: TaskContext, command: Any) -> None: ...

    Raises ConfigError if ``world_model`` is not callable."""
    if not callable(world_model):
        raise ConfigError(f"task(world_model=...): expected a class or factory, "
                          f"got {world_model!r}")

    def mark(func: _Func) -> _Func:
        func.__dict__["world_model"] = world_model  # read by the installer
        return func

    return mark
