"""B2 - level 2: stop / assassin's arm (B2.c).

Stops the servomotors (A6 ``stop``: the joint drives quick-stop, then the safe-torque-off relay
drops; A4 ``stop``: the joint targets held where the joints stand), turns the voltage off (A2),
the wire feed off (A5) and the gas off (A3), in that order, and completes with what each
answered (:class:`chcos.apps.weld.tasks.results.Stopped`).
Used by the assassin E1 at top priority (its links to the A tasks are set high by setpri, so it
pre-empts whoever owns them). Raises WeldTaskError naming the A task that did not comply.
"""

from __future__ import annotations

from typing import Any

from chcos.apps.weld.tasks.common import WeldTaskError
from chcos.apps.weld.tasks.messages import (
    DrivesCommand,
    SetGas,
    SetVolts,
    SetWire,
    StopMotion,
)
from chcos.apps.weld.tasks.results import Stopped
from chcos.user.context import TaskContext

STEPS: tuple[tuple[str, Any], ...] = (
    ("A6", DrivesCommand(stop=True, memorize=None)), ("A4", StopMotion()),
    ("A2", SetVolts(volts=0.0)), ("A5", SetWire(speed=0.0)), ("A3", SetGas(gas="off")))


async def main(ctx: TaskContext, command: Any) -> Stopped:
    """Shut the cell down through the level-1 tasks."""
    answers: dict[str, str] = {}
    failed: list[str] = []
    for port, cmd in STEPS:
        done = await ctx.call(port, cmd)
        answers[port] = done.status.value if done.ok else f"{done.status.value}: {done.error}"
        if not done.ok:
            failed.append(port)
    ctx.world.command["last"] = answers
    if failed:
        raise WeldTaskError(f"B2: stop incomplete, {', '.join(failed)} did not comply: {answers}")
    return Stopped(answers)
