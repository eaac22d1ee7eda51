"""delivery - the message manager's sensory side: messages up links into input ports and
exception taps, readings of devices onto the links leaving them, commands to actuators and
files (tputc, putc).

A sensory message readies the receiver at the link's priority (thesis 6.1.2); a newer message
overwrites an unread one, a queued link keeps a bounded FIFO and refuses a message when full.
:class:`Delivery` is a part of :class:`chcos.messages.manager.MessageManager`.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, TextIO

from chcos.errors import MessageError, QueueOverflow, SensorFailure
from chcos.messages.context import MessageContext
from chcos.tables.messages import EndpointKind, Link, TapPort
from chcos.tables.tasks import TaskEntry

log = logging.getLogger("chcos.messages.manager")


class Delivery:
    """Message transfer for one satellite (see the module doc): the part of the message
    manager that moves sensory messages, device readings and actuator and file output.
    ``base_dir`` is where relative file names are resolved, ``state_dir`` where run state
    lives (default: ``base_dir``)."""

    def __init__(self, ctx: MessageContext, *, base_dir: str | Path | None = None,
                 state_dir: str | Path | None = None) -> None:
        self.ctx = ctx
        self.kernel = ctx.kernel
        self.devices = ctx.devices
        #: where relative file names of installs are resolved
        self.base_dir = Path(base_dir) if base_dir is not None else Path.cwd()
        #: where run state lives beside the map (learned world-model data)
        self.state_dir = Path(state_dir) if state_dir is not None else self.base_dir
        #: (exception task, its tap, its tap links by source task) of every exception task
        self.taps: list[tuple[TaskEntry, TapPort, dict[str, Link]]] = []
        self._files: dict[str, TextIO] = {}
        self._device_links: dict[str, list[Link]] = {}

    # ---- sensory messages (tputc) -----------------------------------------------------------
    def put(self, t: TaskEntry, value: Any) -> int:
        """Send ``value`` from ``t`` up every sensory link leaving it (and into exception taps).

        Never blocks. Returns how many links took it. Raises QueueOverflow (after delivering to
        every other link) if a queued link was full.
        """
        links = t.up_links
        if len(links) == 1 and not t.tapped:  # one reader, no exception task: no gathering
            return self.deliver(links[0], value)
        n = 0
        overflow: QueueOverflow | None = None
        for link in links:
            try:
                n += self.deliver(link, value)
            except QueueOverflow as exc:
                overflow = exc
        if t.tapped:
            self._tap(t, value)
        if overflow is not None:
            raise overflow
        return n

    def deliver(self, link: Link, value: Any) -> int:
        """Put ``value`` into ``link``'s destination port and wake a receiver waiting on it, at
        the higher of its own and the link's priority (through :meth:`Kernel.wake`).

        1 if the link took it, 0 if it is suspended (a count: :meth:`put` returns it). Raises
        QueueOverflow for a full queued link, MessageError for a link without an input port.
        """
        if link.suspended:
            link.refused += 1
            return 0
        if link.remote:  # the communications manager batches it (or raises: not counted)
            if self.ctx.comm.sensory(link, value):  # it replaced one waiting to leave
                link.overwritten += 1
            link.sent += 1
            return 1
        port = link.port
        if port is None:
            raise MessageError(f"sensory link {link.name} has no input port")
        kernel = self.kernel
        hooks = kernel.hooks
        # the time sent is kept only for an instrument measuring latency
        sent_at = kernel.clock.now() if hooks.h_delivered else None
        if port.store(value, sent_at):  # a newest-wins port had an unread one
            link.overwritten += 1
            if hooks.h_overwritten:
                hooks.notify(hooks.h_overwritten, "message_overwritten", link)
        link.sent += 1
        if hooks.h_sent:
            hooks.notify(hooks.h_sent, "message_sent", link)
        w = port.reader
        if port in w.wait_ports and (w.wake_filter is None or self._wanted(w, link.src, value)):
            prio = w.prio_src.priority  # the task's base priority (TaskEntry.base_prio)
            kernel.wake(w, prio if prio > link.priority else link.priority)
        return 1

    @staticmethod
    def _wanted(w: TaskEntry, source: str, value: Any) -> bool:
        """Whether ``w``'s ``wait_any(when=...)`` filter lets this message wake it (a filter
        that raises lets it through: a failure is never masked)."""
        f = w.wake_filter
        try:
            return f is None or bool(f(source, value))
        except Exception:
            log.exception("wake filter of %s failed on a message from %s", w.name, source)
            return True

    def _tap(self, t: TaskEntry, value: Any) -> None:
        for _exc_task, tap, links in self.taps:
            link = links.get(t.name)
            if link is None or link.suspended:
                continue
            if link.remote:
                link.sent += 1
                self.ctx.comm.tap(link, t.name, value)
                continue
            self.deliver_tap(link, tap, t.name, value)

    def deliver_tap(self, link: Link, tap: TapPort, source: str, value: Any) -> None:
        """Put ``source``'s message into an exception task's tap and ready the task."""
        kernel = self.kernel
        if tap.store_from(source, value, kernel.clock.now()):
            link.overwritten += 1
        link.sent += 1
        w = tap.waiter
        if w is not None and (w.wake_filter is None or self._wanted(w, source, value)):
            tap.waiter = None
            kernel.wake(w, max(w.base_prio, link.priority), tap)

    def superseded(self, link: Link, n: int) -> None:
        """``n`` messages of remote ``link`` were replaced on the sender's satellite before
        they left (the communications manager saw the gap in their numbers): count them as
        sent and overwritten on this satellite's copy of the link."""
        link.sent += n
        link.overwritten += n

    def taken(self, link: Link, sent_at: float | None) -> None:
        """The receiver read a message of ``link`` (an input port's: Link.delivered counts it
        by itself), sent at clock time ``sent_at``: feed the latency instruments. A message
        sent while no instrument listened to deliveries (``sent_at`` None) is not measured."""
        kernel = self.kernel
        hooks = kernel.hooks
        if hooks.h_delivered and sent_at is not None:
            hooks.notify(hooks.h_delivered, "message_delivered", link,
                         kernel.clock.now() - sent_at)

    # ---- devices: readings up their links, e-stop -------------------------------------------
    def add_device_link(self, link: Link) -> None:
        """Route the readings of device ``link.src`` into sensory link ``link`` (at install)."""
        self._device_links.setdefault(link.src, []).append(link)

    def reading(self, device: str, value: Any) -> bool:
        """Devtab listener: a new reading of sensor ``device`` goes up every sensory link
        leaving it, readying the tasks waiting for it. True if it overwrote an unread message
        (on a newest-wins link: a queued link keeps it behind the unread ones, and refuses it
        when full). Raises QueueOverflow (after delivering to every other link) if a queued
        link was full."""
        over = False
        overflow: QueueOverflow | None = None
        for link in self._device_links.get(device, ()):
            # an unread message on a newest-wins port is overwritten (a queued link keeps it,
            # a suspended one refuses the new one): the link counts it
            before = link.overwritten
            try:
                self.deliver(link, value)
            except QueueOverflow as exc:
                overflow = exc
            if link.overwritten != before:
                over = True
        if overflow is not None:
            raise overflow
        return over

    def sensor_failed(self, device: str, failure: SensorFailure) -> None:
        """Devtab listener: sensor ``device`` failed or went stale; every task waiting on one of
        its links gets ``failure`` thrown in."""
        kernel = self.kernel
        for link in self._device_links.get(device, ()):
            port = link.port
            if port is not None and port in port.reader.wait_ports:
                w = port.reader
                kernel.wake(w, max(w.base_prio, link.priority), exc=failure)

    def estop(self, by: str, reason: str) -> int:
        """Emergency stop by ``by``: every other satellite is told, every local actuator with a
        safe value gets it at once; then the event is reported (instruments, log). Returns how
        many were written here."""
        self.ctx.comm.estop(reason)
        n = self.devices.estop(reason)
        self.ctx.event("estop", f"{by}: {reason}")
        return n

    # ---- command output to actuators and files (putc) ---------------------------------------
    def write(self, t: TaskEntry, link: Link, value: Any) -> None:
        """Send ``value`` down command link ``link`` to an actuator or a file, without blocking.

        Raises MessageError if the link leads to a task (use open), DeviceError if the actuator
        refuses the value (outside its limits, failed device).
        """
        if link.suspended:
            link.refused += 1
            raise MessageError(f"link {link.name} is suspended")
        if link.dst_kind is EndpointKind.DEVICE:
            self.devices.write(link.dst, value, t.name)
        elif link.dst_kind is EndpointKind.FILE:
            self.write_file(link.dst, value)
        else:
            raise MessageError(
                f"{link.name} is a command link to task {link.dst}: invoke it, do not write to it")
        link.sent += 1  # and delivered (Link.delivered: sent, on a link to an actuator or file)

    def resolve_path(self, name: str) -> Path:
        """A file endpoint's path: relative names are relative to the system's base directory."""
        p = Path(name)
        return p if p.is_absolute() else self.base_dir / p

    def write_file(self, path: str, value: Any) -> None:
        """Append ``value`` as one line to the file at ``path`` (kept open, line-buffered)."""
        fh = self._files.get(path)
        if fh is None:
            try:
                fh = open(self.resolve_path(path), "a", buffering=1,  # noqa: SIM115 - kept open
                          encoding="utf-8")
            except OSError as exc:
                raise MessageError(f"cannot open output file {path}: {exc}") from exc
            self._files[path] = fh
        fh.write(f"{value}\n")

    def close_files(self) -> None:
        """Close every output file."""
        for fh in self._files.values():
            fh.close()
        self._files.clear()
