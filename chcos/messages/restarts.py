"""restarts - the restart policies of tasks installed with ``--restart``: ``always`` restarts
an abnormally ended task after its back-off with its last command; ``on-recovery`` waits until
every device it reads or commands is healthy again (Devtab's health listener tells).
"""

from __future__ import annotations

from typing import Any

from chcos.messages.ownership import Ownership
from chcos.tables.messages import EndpointKind
from chcos.tables.tasks import TaskEntry


class Restarts(Ownership):
    """The restart policies, on top of :class:`Ownership` (see the module doc)."""

    def _plan_restart(self, t: TaskEntry, err: Any) -> None:
        """After an abnormal end with nobody to take the task over: apply its restart policy."""
        if t.restart == "never" or not self.is_local(t.machine):
            return
        if t.restart == "always":
            self._restart_later(t, f"restart=always after {type(err).__name__}")
            return
        bad = self._unhealthy_devices(t)
        if not bad:  # on-recovery: it did not end because a device failed
            self.event("restart-skipped", f"{t.name}: ended abnormally with its devices healthy "
                                          "(restart=on-recovery restarts only after a device "
                                          "failure)")
            return
        t.waiting_devices = frozenset(bad)
        self.event("restart-waiting", f"{t.name}: waiting for {', '.join(sorted(bad))} to be "
                                      "healthy again")

    def _unhealthy_devices(self, t: TaskEntry) -> set[str]:
        names = {p.link.src for p in t.in_ports if p.link.src_kind is EndpointKind.DEVICE}
        names |= {lk.dst for lk in t.out_links if lk.dst_kind is EndpointKind.DEVICE}
        return {n for n in names if not self.devices.healthy(n)}

    def _restart_later(self, t: TaskEntry, why: str) -> None:
        if t.restart_timer is not None:
            return

        def fire() -> None:
            t.restart_timer = None
            if t.coro is not None or t.owner is not None or t.frozen:
                return  # somebody took it over meanwhile: the owner decides
            t.restarts += 1
            self.event("restart", f"{t.name} restarted ({why}) with its last command "
                                  f"{t.last_command!r}")
            self._activate(t, t.last_command, t.default_prio)

        t.restart_timer = self.kernel.call_later(t.backoff, fire)

    def device_health(self, device: str, healthy: bool, cause: str) -> None:
        """Devtab health listener: restart the on-recovery tasks waiting for ``device``."""
        if not healthy:
            return
        for t in self.tsktab:
            if device in t.waiting_devices:
                if any(not self.devices.healthy(n) for n in t.waiting_devices):
                    continue
                t.waiting_devices = frozenset()
                self._restart_later(t, f"restart=on-recovery: {device} healthy again")
