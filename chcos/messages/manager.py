"""manager - the message manager: moves messages on links and keeps command ownership.

It is the layer that readies tasks (thesis 6.1.2): a sensory message readies the receiver at the
link's priority; ``open`` (topen) makes the caller the owner of a lower task, pre-empting a lower
priority owner, who is told, or queueing the caller; ``close`` (tclose) hands the task to the best
waiter or suspends it; the end of an activation reports normal or abnormal completion (teotsk) to
the owner. Devices, files and the host are link ends too.

The manager is built in parts, one module each: :mod:`~chcos.messages.delivery` (sensory
messages, device readings, actuator and file output), :mod:`~chcos.messages.ownership`
(topen/tclose/teotsk, pre-emption, suspension), :mod:`~chcos.messages.restarts` (restart
policies) and :mod:`~chcos.messages.remote` (other satellites, world-model queries). Its
collaborators come in through the constructor: the device table as :class:`Devices`, the
communications manager as :class:`Comm` (absent in a one-process system).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from chcos.kernel.scheduler import Kernel
from chcos.messages.protocols import Comm, Devices, NoComm
from chcos.messages.remote import Remote
from chcos.messages.restarts import Restarts
from chcos.tables.messages import Msgtab
from chcos.tables.tasks import TaskEntry, Tsktab

__all__ = ["Comm", "Devices", "MessageManager", "NoComm"]


class MessageManager(Remote, Restarts):
    """Message transfer and ownership for one satellite's tables. ``devices`` is the device
    table, ``comm`` the link to the other satellites (None: a one-process system), ``local``
    the machines this process hosts (None: all), ``base_dir`` where relative file names are
    resolved, ``state_dir`` where run state lives beside the map (default: ``base_dir``).

    The owner of the composition (:class:`chcos.system.embedded.System`) connects it to the
    kernel (:meth:`activation_ended` as the end handler) and to the device table (readings,
    sensor failures, health)."""

    def __init__(self, kernel: Kernel, tsktab: Tsktab, msgtab: Msgtab, devices: Devices,
                 comm: Comm | None = None, *, local: Iterable[int] | None = None,
                 base_dir: str | Path | None = None, state_dir: str | Path | None = None) -> None:
        super().__init__(kernel, tsktab, msgtab, devices, comm, local=local, base_dir=base_dir,
                         state_dir=state_dir)
        self._qseq = 0
        self._ask_seq = 0
        self._asks: dict[int, tuple[TaskEntry, int]] = {}
