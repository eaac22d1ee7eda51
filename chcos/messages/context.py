"""context - what every part of one satellite's message manager works on.

The message manager (:mod:`chcos.messages.manager`) is composed of parts, one object each:
delivery, ownership (with its restart policies) and the answers to and from other satellites.
They share one :class:`MessageContext`: the kernel, the task and message tables, the device
table, the link to the other satellites and which machines run in this process.
"""

from __future__ import annotations

from collections.abc import Iterable

from chcos.kernel.scheduler import Kernel
from chcos.messages.protocols import Comm, Devices, NoComm
from chcos.tables.messages import EndpointKind, Link, Msgtab
from chcos.tables.tasks import TaskEntry, Tsktab


class MessageContext:
    """One satellite's tables and collaborators, shared by the parts of its message manager.
    ``comm`` is None in a one-process system; ``local`` the machines hosted here (None: all)."""

    def __init__(self, kernel: Kernel, tsktab: Tsktab, msgtab: Msgtab, devices: Devices,
                 comm: Comm | None = None, local: Iterable[int] | None = None) -> None:
        self.kernel = kernel
        self.tsktab = tsktab
        self.msgtab = msgtab
        self.devices = devices
        #: the link to the other satellites; a composition root that builds it after the
        #: message manager (it needs the manager for what comes in) sets it before the kernel
        #: runs, for every part at once
        self.comm: Comm = comm if comm is not None else NoComm()
        #: machines hosted here (None: every machine, a one-process system)
        self.local: frozenset[int] | None = frozenset(local) if local is not None else None

    def is_local(self, machine: int) -> bool:
        """True if ``machine`` runs in this process."""
        return self.local is None or machine in self.local

    def remote_task(self, t: TaskEntry | None) -> bool:
        """True if ``t`` is a task that runs on another satellite."""
        return t is not None and self.local is not None and t.machine not in self.local

    def caller(self, link: Link) -> TaskEntry | None:
        """The task at the source end of ``link``, None for a device, file or the host."""
        if link.src_kind is EndpointKind.TASK and link.src in self.tsktab:
            return self.tsktab.get(link.src)
        return None

    def event(self, kind: str, detail: str) -> None:
        """Report a system event to the instruments and the log (see :meth:`Kernel.event`)."""
        self.kernel.event(kind, detail)
