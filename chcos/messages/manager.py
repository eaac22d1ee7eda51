"""manager - the message manager: moves messages on links and keeps command ownership.

It is the layer that readies tasks (thesis 6.1.2): a sensory message readies the receiver at the
link's priority; ``open`` (topen) makes the caller the owner of a lower task, pre-empting a lower
priority owner, who is told, or queueing the caller; ``close`` (tclose) hands the task to the best
waiter or suspends it; the end of an activation reports normal or abnormal completion (teotsk) to
the owner. Devices, files and the host are link ends too.

The manager is composed of parts, one object and one module each, sharing one
:class:`~chcos.messages.context.MessageContext`: :attr:`MessageManager.delivery`
(:mod:`~chcos.messages.delivery`: sensory messages, device readings, actuator and file output),
:attr:`MessageManager.ownership` (:mod:`~chcos.messages.ownership`: topen/tclose/teotsk,
pre-emption, suspension, and its restart policies, :mod:`~chcos.messages.restarts`) and
:attr:`MessageManager.remote` (:mod:`~chcos.messages.remote`: other satellites, world-model
queries). Its collaborators come in through the constructor: the device table as
:class:`Devices`, the communications manager as :class:`Comm` (absent in a one-process system).
The manager's methods are the parts' own (see each for what it does and raises).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from chcos.kernel.scheduler import Kernel
from chcos.messages.context import MessageContext
from chcos.messages.delivery import Delivery
from chcos.messages.ownership import Ownership
from chcos.messages.protocols import Comm, Devices, NoComm
from chcos.messages.remote import Remote
from chcos.tables.messages import Link, Msgtab, TapPort
from chcos.tables.tasks import TaskEntry, Tsktab

__all__ = ["Comm", "Devices", "MessageManager", "NoComm"]


class MessageManager:
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
        self.ctx = MessageContext(kernel, tsktab, msgtab, devices, comm, local)
        self.kernel = kernel
        self.tsktab = tsktab
        self.msgtab = msgtab
        self.devices = devices
        #: sensory messages, device readings, actuator and file output
        self.delivery = Delivery(self.ctx, base_dir=base_dir, state_dir=state_dir)
        #: command ownership, the end of activations, suspension, restarts
        self.ownership = Ownership(self.ctx)
        #: answers to and from other satellites, world-model queries across them
        self.remote = Remote(self.ctx, self.ownership)
        d, o, r = self.delivery, self.ownership, self.remote
        #: the delivery part's list of exception tasks (the installer adds to it)
        self.taps: list[tuple[TaskEntry, TapPort, dict[str, Link]]] = d.taps
        # what the layers above call, as the parts' own bound methods
        self.put = d.put
        self.deliver = d.deliver
        self.taken = d.taken
        self.deliver_tap = d.deliver_tap
        self.superseded = d.superseded
        self.add_device_link = d.add_device_link
        self.reading = d.reading
        self.sensor_failed = d.sensor_failed
        self.estop = d.estop
        self.write = d.write
        self.resolve_path = d.resolve_path
        self.close_files = d.close_files
        self.open = o.open
        self.close = o.close
        self.complete = o.complete
        self.activation_ended = o.activation_ended
        self.start_standing = o.start_standing
        self.release_subordinates = o.release_subordinates
        self.suspend_task = o.suspend_task
        self.resume_task = o.resume_task
        self.reset_task = o.reset_task
        self.wipe = o.wipe
        self.resetpri = o.resetpri
        self.setpri = o.setpri
        self.done_now = o.done_now
        self.device_health = o.restarts.device_health
        self.remote_open = r.remote_open
        self.open_answer = r.open_answer
        self.remote_report = r.remote_report
        self.world_answer = r.world_answer
        self.ask_remote = r.ask_remote
        self.ask_answered = r.ask_answered
        self.satellite_lost = r.satellite_lost
        self.queries_pending = r.queries_pending
        self.is_local = self.ctx.is_local
        self.event = self.ctx.event

    @property
    def comm(self) -> Comm:
        """The link to the other satellites (a :class:`NoComm` in a one-process system). A
        composition root that builds it after this manager sets it here before the kernel
        runs: every part uses it from then on."""
        return self.ctx.comm

    @comm.setter
    def comm(self, comm: Comm) -> None:
        self.ctx.comm = comm

    @property
    def local(self) -> frozenset[int] | None:
        """The machines hosted here (None: every machine, a one-process system)."""
        return self.ctx.local

    @property
    def state_dir(self) -> Path:
        """Where run state lives beside the map (learned world-model data)."""
        return self.delivery.state_dir
