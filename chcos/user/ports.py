"""ports - the base of the task handle: the task's Usrtab (eight input ports, eight output
ports) looked up by index or by the peer's name, and the newest command of its owner."""

from __future__ import annotations

from typing import Any

from chcos.errors import MessageError
from chcos.kernel.scheduler import Kernel
from chcos.messages.manager import MessageManager
from chcos.tables.messages import EndpointKind, InPort, Link
from chcos.tables.tasks import TaskEntry

Port = int | str


class TaskHandle:
    """What every part of :class:`chcos.user.context.TaskContext` stands on: the task's entry,
    the kernel and the message manager, and the port lookup."""

    """The handle a task's code uses for every system call. One per task, made at install."""

    def __init__(self, task: TaskEntry, kernel: Kernel, msgmgr: MessageManager) -> None:
        self._t = task
        self._k = kernel
        self._mm = msgmgr
        self._deliver = msgmgr.deliver  # put's hot path: one attribute less per message
        #: input ports found so far, by index and by source name (read's hot path, one lookup:
        #: a dict, so a negative index misses, and so does anything unhashable). A task's
        #: ports are only ever appended (at its install), so what is found stays right. A key
        #: equal to one here finds it too, as in any dict (True is port 1)
        self._in_found: dict[int | str, InPort] = {}
        self._out_named: dict[str, Link] = {}
        #: the input ports in read_any's order (highest link priority, then lowest port), and
        #: the :attr:`Link.epoch` it was made at (read_any makes it again after any setpri)
        self._any_order: tuple[InPort, ...] = ()
        self._any_epoch = -1

    def take_command(self) -> Any:
        """The owner's newest command to this running activation (it becomes :attr:`command`).
        Raises MessageError if there is none (see :attr:`has_command`)."""
        t = self._t
        if t.new_command is None:
            raise MessageError(f"task {t.name}: no new command from its owner")
        (cmd,), t.new_command = t.new_command, None
        t.command = t.last_command = cmd
        return cmd

    @property
    def inputs(self) -> list[str]:
        """Names of the sources on input ports 0..n-1."""
        return [p.link.src for p in self._t.in_ports]

    @property
    def outputs(self) -> list[str]:
        """Names of the destinations on output ports 0..n-1."""
        return [lk.dst for lk in self._t.out_links]

    def _in(self, port: Port) -> InPort:
        ports = self._t.in_ports
        if not isinstance(port, str):
            # an index, or anything equal to one (True, 1.0), as read's dict finds it
            if port in range(len(ports)):
                p = self._in_found[port] = ports[int(port)]
                return p
            raise MessageError(f"task {self._t.name} has no input port {port} "
                               f"(it has {len(ports)}: {', '.join(self.inputs) or 'none'})")
        for p in ports:
            if p.link.src == port:
                self._in_found[port] = p
                return p
        raise MessageError(f"task {self._t.name} has no input from {port!r} "
                           f"(inputs: {', '.join(self.inputs) or 'none'})")

    def _out(self, port: Port) -> Link:
        links = self._t.out_links
        if isinstance(port, int):
            if 0 <= port < len(links):
                return links[port]
            raise MessageError(f"task {self._t.name} has no output port {port} "
                               f"(it has {len(links)}: {', '.join(self.outputs) or 'none'})")
        for lk in links:
            if lk.dst == port:
                self._out_named[port] = lk
                return lk
        special = self._t.special_links.get(port)
        if special is not None:
            return special
        raise MessageError(f"task {self._t.name} has no output to {port!r} "
                           f"(outputs: {', '.join(self.outputs) or 'none'})")

    def _task_link(self, port: Port) -> Link:
        link = self._out(port)
        if link.dst_kind is not EndpointKind.TASK:
            raise MessageError(f"{link.name} leads to {link.dst_kind.value} {link.dst}, "
                               "not to a task: write() to it")
        return link
