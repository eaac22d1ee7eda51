"""restarts - the restart policies of tasks installed with ``--restart``: ``always`` restarts
an abnormally ended task after its back-off with its last command; ``on-recovery`` waits until
every device it reads or commands is healthy again (Devtab's health listener tells).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from chcos.messages.context import MessageContext
from chcos.tables.messages import EndpointKind
from chcos.tables.tasks import TaskEntry

#: How a restart begins an activation: ``activate(task, command, priority)``.
Activate = Callable[[TaskEntry, Any, int], None]


class Restarts:
    """The restart policies (see the module doc), a part of
    :class:`chcos.messages.ownership.Ownership`, which restarts a task through ``activate``."""

    def __init__(self, ctx: MessageContext, activate: Activate) -> None:
        self.ctx = ctx
        self._activate = activate

    def plan(self, t: TaskEntry, err: Any) -> None:
        """After an abnormal end with nobody to take the task over: apply its restart policy."""
        if t.restart == "never" or not self.ctx.is_local(t.machine):
            return
        if t.restart == "always":
            self._restart_later(t, f"restart=always after {type(err).__name__}")
            return
        bad = self._unhealthy_devices(t)
        if not bad:  # on-recovery: it did not end because a device failed
            self.ctx.event("restart-skipped",
                           f"{t.name}: ended abnormally with its devices healthy "
                           "(restart=on-recovery restarts only after a device failure)")
            return
        t.waiting_devices = frozenset(bad)
        self.ctx.event("restart-waiting",
                       f"{t.name}: waiting for {', '.join(sorted(bad))} to be healthy again")

    def _unhealthy_devices(self, t: TaskEntry) -> set[str]:
        names = {p.link.src for p in t.in_ports if p.link.src_kind is EndpointKind.DEVICE}
        names |= {lk.dst for lk in t.out_links if lk.dst_kind is EndpointKind.DEVICE}
        return {n for n in names if not self.ctx.devices.healthy(n)}

    def _restart_later(self, t: TaskEntry, why: str) -> None:
        if t.restart_timer is not None:
            return

        def fire() -> None:
            t.restart_timer = None
            if t.coro is not None or t.owner is not None or t.frozen:
                return  # somebody took it over meanwhile: the owner decides
            t.restarts += 1
            self.ctx.event("restart", f"{t.name} restarted ({why}) with its last command "
                                  f"{t.last_command!r}")
            self._activate(t, t.last_command, t.default_prio)

        t.restart_timer = self.ctx.kernel.call_later(t.backoff, fire)

    def device_health(self, device: str, healthy: bool, cause: str) -> None:
        """Devtab health listener: restart the on-recovery tasks waiting for ``device``."""
        if not healthy:
            return
        for t in self.ctx.tsktab:
            if device in t.waiting_devices:
                if any(not self.ctx.devices.healthy(n) for n in t.waiting_devices):
                    continue
                t.waiting_devices = frozenset()
                self._restart_later(t, f"restart=on-recovery: {device} healthy again")
