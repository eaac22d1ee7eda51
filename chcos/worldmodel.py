"""worldmodel - each task's own small world model (thesis 5.4).

Two data structures, as the thesis asks: a *sensory* one (processed sensory information the task
has seen) and a *command* one (what the task is executing). The owning task writes both directly;
another task may only *ask*, through a query on a link between the two (``ctx.ask``), which the
owning task's model answers with :meth:`WorldModel.answer`. Subclass it to give context and
predictions (e.g. "high temperature is expected while welding") or to recognise patterns.
"""

from __future__ import annotations

from typing import Any

from chcos.errors import MessageError


class WorldModel:
    """A task's world model: ``sensory`` and ``command`` dictionaries plus a query interface."""

    def __init__(self) -> None:
        self.sensory: dict[str, Any] = {}
        self.command: dict[str, Any] = {}

    def answer(self, topic: str, *args: Any) -> Any:
        """Answer another task's query about ``topic``.

        The default looks ``topic`` up in the sensory, then the command structure; a subclass may
        compute context or predictions. Raises MessageError if the model knows nothing about it.
        """
        if topic in self.sensory:
            return self.sensory[topic]
        if topic in self.command:
            return self.command[topic]
        raise MessageError(f"world model has nothing on {topic!r}")

    def snapshot(self) -> dict[str, dict[str, Any]]:
        """A shallow copy of both structures (for maps and viewers)."""
        return {"sensory": dict(self.sensory), "command": dict(self.command)}
