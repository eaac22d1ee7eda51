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
    the kernel and the message manager, and the port lookup. One per task, made at install."""

    def __init__(self, task: TaskEntry, kernel: Kernel, msgmgr: MessageManager) -> None:
        self._t = task
        self._k = kernel
        self._mm = msgmgr

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
        """Input ``port``, by index or by the source's name; raises MessageError naming the
        task and its inputs if there is no such port."""
        ports = self._t.in_ports
        if port.__class__ is int:
            if 0 <= port < len(ports):
                return ports[port]
            raise MessageError(f"task {self._t.name} has no input port {port} "
                               f"(it has {len(ports)}: {', '.join(self.inputs) or 'none'})")
        if type(port) is str:
            for p in ports:
                if p.link.src == port:
                    return p
            raise MessageError(f"task {self._t.name} has no input from {port!r} "
                               f"(inputs: {', '.join(self.inputs) or 'none'})")
        raise MessageError(f"task {self._t.name}: an input port is an index or a source name, "
                           f"not {port!r}")

    def _out(self, port: Port) -> Link:
        """Output ``port``, by index or by the destination's name (an assassin's special link
        by its target's name too); raises MessageError naming the task and its outputs if
        there is no such port."""
        links = self._t.out_links
        if type(port) is int:
            if 0 <= port < len(links):
                return links[port]
            raise MessageError(f"task {self._t.name} has no output port {port} "
                               f"(it has {len(links)}: {', '.join(self.outputs) or 'none'})")
        if type(port) is str:
            for lk in links:
                if lk.dst == port:
                    return lk
            special = self._t.special_links.get(port)
            if special is not None:
                return special
            raise MessageError(f"task {self._t.name} has no output to {port!r} "
                               f"(outputs: {', '.join(self.outputs) or 'none'})")
        raise MessageError(f"task {self._t.name}: an output port is an index or a destination "
                           f"name, not {port!r}")

    def _task_link(self, port: Port) -> Link:
        link = self._out(port)
        if link.dst_kind is not EndpointKind.TASK:
            raise MessageError(f"{link.name} leads to {link.dst_kind.value} {link.dst}, "
                               "not to a task: write() to it")
        return link
