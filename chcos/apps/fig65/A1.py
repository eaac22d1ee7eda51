"""A1 - user driver for S1 and S2, commanding actuator M1 (figure 6.5)."""

from typing import Any

from chcos.apps.fig65.common import condense
from chcos.user.context import TaskContext


async def main(ctx: TaskContext, command: Any) -> Any:
    """Keep M1 in step with S1/S2 and report every fifth reading to B1, until shut down."""
    while await condense(ctx, actuator="M1") != "shut down":
        pass
    return "shut down"
