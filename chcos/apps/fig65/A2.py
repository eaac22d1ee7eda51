"""A2 - user driver for S3, commanding actuator M2 (figure 6.5)."""

from typing import Any

from chcos.apps.fig65.common import condense
from chcos.user.context import TaskContext


async def main(ctx: TaskContext, command: Any) -> Any:
    """Keep M2 in step with S3 and report every fifth reading to B1 and B2, until shut down."""
    while await condense(ctx, actuator="M2") != "shut down":
        pass
    return "shut down"
