"""installer - ``install``: places a task on a machine with its input sources and output
destinations, and makes the implicit links (exception taps, assassin links, the host's link).

It checks everything first and changes nothing unless all is well: the name is new (tasks are
never removed), the machine is loaded, every peer exists and is of the right kind (sensory
inputs come from sensors, files, terminals or tasks; command outputs go to actuators, files or
tasks), at most eight of each, and every link keeps the hierarchy: sensory links go to a
strictly higher level, command links to a strictly lower one (levels follow from the links, or
``--level`` places a task higher). Then it enters the task, its links and ports, the exception
taps and assassin links, and reports the change (the system manager marks sysfile.map for
writing).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from chcos.errors import InstallError, TaskError
from chcos.helpers import NAME_PATTERN
from chcos.system.cmdline import Install
from chcos.system.loader import resolve
from chcos.system.ports import Devices, Messages, Setup
from chcos.tables.messages import (
    DEFAULT_COMMAND_PRIORITY,
    DEFAULT_SENSORY_PRIORITY,
    PORTS,
    TOP_PRIORITY,
    EndpointKind,
    Link,
    LinkType,
    Msgtab,
    TapPort,
    in_port,
)
from chcos.tables.tasks import Role, TaskEntry, TaskFunc, Tsktab
from chcos.user.context import TaskContext
from chcos.user.worldmodel import WorldModel


@dataclass(frozen=True)
class _Peer:
    name: str
    kind: EndpointKind
    level: int
    machine: int
    direction: str = ""  # sensor/actuator for devices, "terminal" for terminals


async def _elsewhere(ctx: TaskContext, command: Any) -> None:
    """Stands for the code of a task that runs on another satellite (never activated here)."""
    raise TaskError(f"task {ctx.name} runs on machine {ctx.machine}, not on this satellite")


def is_path(name: str) -> bool:
    """True if an install argument names a file or terminal rather than a task or device."""
    return "/" in name or name.startswith(".")



class Installer:
    """The install half of TSK0: checks and enters tasks and their links. ``machines`` is the
    system manager's set of loaded machines (shared); ``changed(kind, detail)`` reports a
    change of the tables."""

    def __init__(self, *, tsktab: Tsktab, msgtab: Msgtab, msgmgr: Messages, devtab: Devices,
                 setup: Setup, machines: set[int], changed: Callable[[str, str], None]) -> None:
        self.tsktab = tsktab
        self.msgtab = msgtab
        self.msgmgr = msgmgr
        self.devtab = devtab
        self.setup = setup
        self.machines = machines
        self.changed = changed
        self.installs: list[Install] = []
        self.host_links: dict[str, Link] = {}
        self.terminals: dict[str, list[Link]] = {}
        self._assassins: list[TaskEntry] = []   # in install order (see _exception_wiring)

    def _path(self, name: str) -> Path:
        return self.msgmgr.resolve_path(name)

    def _peer(self, name: str) -> _Peer | None:
        if name in self.tsktab:
            t = self.tsktab.get(name)
            return _Peer(name, EndpointKind.TASK, t.level, t.machine)
        if name in self.devtab:
            d = self.devtab.get(name).spec
            return _Peer(name, EndpointKind.DEVICE, 0, d.machine, d.direction)
        if name.startswith(("/dev/tty", "/dev/pts/")):
            return _Peer(name, EndpointKind.FILE, 0, -1, "terminal")
        if is_path(name):
            return _Peer(name, EndpointKind.FILE, 0, -1, "file")
        return None

    # ---- install ----------------------------------------------------------------------------
    def check_install(self, req: Install) -> tuple[TaskFunc, int, list[_Peer], list[_Peer]]:
        """Validate ``req`` without changing anything; returns (function, level, inputs,
        outputs). Raises InstallError listing every problem found."""
        errs: list[str] = []
        if not NAME_PATTERN.fullmatch(req.name):
            errs.append(f"task name {req.name!r} is not a valid name (letters, digits, _ . -)")
        elif req.name in self.tsktab:
            t = self.tsktab.get(req.name)
            errs.append(f"task {req.name} is already installed on machine {t.machine} "
                        "(tasks are never removed or replaced)")
        elif req.name in self.devtab:
            errs.append(f"{req.name} is a device in Devtab; a task cannot take its name")
        if req.machine not in self.machines:
            errs.append(f"machine {req.machine} is not loaded "
                        f"(run 'install -m{req.machine} sysfile' first)")
        for what, names in (("inputs", req.inputs), ("outputs", req.outputs)):
            if len(names) > PORTS:
                errs.append(f"{len(names)} {what}: a task has at most {PORTS}")
            dup = sorted({n for n in names if names.count(n) > 1})
            if dup:
                errs.append(f"{what} name {', '.join(dup)} more than once")
        if req.role not in ("task", "exception", "assassin"):
            errs.append(f"role {req.role!r}: expected task, exception or assassin")
        for src in req.queued:
            if src not in req.inputs:
                errs.append(f"--queue {src}: {src} is not an input of {req.name}")
        ins: list[_Peer] = []
        outs: list[_Peer] = []
        for n in req.inputs:
            p = self._peer(n)
            if n == req.name:
                errs.append(f"sensory link {n}/{req.name}: a task cannot read itself")
            elif p is None:
                errs.append(f"input {n} of {req.name} does not exist "
                            "(no task, device, file or terminal of that name)")
            elif p.kind is EndpointKind.DEVICE and p.direction != "sensor":
                errs.append(f"input {n} of {req.name} is an actuator: sensory links come from "
                            "sensors, files, terminals or lower tasks")
            elif p.direction == "file" and not self._path(n).is_file():
                errs.append(f"input file {n} of {req.name} does not exist "
                            f"(looked for {self._path(n)})")
            else:
                ins.append(p)
        for n in req.outputs:
            p = self._peer(n)
            if n == req.name:
                errs.append(f"command link {req.name}/{n}: a task cannot command itself")
            elif p is None:
                errs.append(f"output {n} of {req.name} does not exist "
                            "(no task, device or file of that name)")
            elif p.kind is EndpointKind.DEVICE and p.direction != "actuator":
                errs.append(f"output {n} of {req.name} is a sensor: command links go to "
                            "actuators, files or lower tasks")
            elif p.direction == "terminal":
                errs.append(f"output {n} of {req.name} is a terminal: terminals are inputs")
            elif p.direction == "file" and not self._path(n).parent.is_dir():
                errs.append(f"output file {n} of {req.name}: directory "
                            f"{self._path(n).parent} does not exist")
            else:
                outs.append(p)
        peers = ins + outs
        level = req.level if req.level is not None else 1 + max((p.level for p in peers),
                                                                 default=0)
        for p in ins:
            if p.level >= level:
                errs.append(f"sensory link {p.name}/{req.name} must go up to a strictly higher "
                            f"level: {p.name} is at level {p.level}, {req.name} would be at "
                            f"level {level}")
        for p in outs:
            if p.level >= level:
                errs.append(f"command link {req.name}/{p.name} must go down to a strictly lower "
                            f"level: {p.name} is at level {p.level}, {req.name} would be at "
                            f"level {level}")
        func: TaskFunc | None = None
        if not self.msgmgr.is_local(req.machine):
            func = _elsewhere  # its own satellite loads the code
        else:
            try:
                func = resolve(req.code or req.name, self.setup.task_path)
            except InstallError as exc:
                errs.append(str(exc))
        if errs or func is None:
            raise InstallError(f"install {req.name} refused, tables unchanged:\n  - "
                               + "\n  - ".join(errs))
        return func, level, ins, outs

    def install(self, req: Install) -> TaskEntry:
        """Install a task (see the module doc). Raises InstallError (tables unchanged)."""
        func, level, ins, outs = self.check_install(req)
        role = Role(req.role)
        if getattr(func, "chcos_system_driver", False):
            role = Role.SYSTEM
        t = TaskEntry(tid=self.tsktab.next_tid(), name=req.name, machine=req.machine, level=level,
                      func=func, code=req.code, role=role, params=dict(req.params),
                      prio=DEFAULT_COMMAND_PRIORITY)
        factory = getattr(func, "world_model", None)
        t.world = factory() if callable(factory) else WorldModel()
        t.ctx = self.setup.context(t)
        t.default_prio = DEFAULT_COMMAND_PRIORITY
        t.standing, t.restart, t.backoff = req.standing, req.restart, req.backoff
        self.tsktab.add(t)
        for i, p in enumerate(ins):
            prio = (self.devtab.get(p.name).spec.priority if p.kind is EndpointKind.DEVICE
                    else DEFAULT_SENSORY_PRIORITY)
            link = self.link(p.name, t.name, LinkType.SENSORY, prio, p.kind, EndpointKind.TASK,
                              p.machine, t.machine, queued=req.queued.get(p.name, 0))
            link.dst_port = i
            port = in_port(link, i, t)
            link.port = port
            t.in_ports.append(port)
            if p.kind is EndpointKind.TASK:
                self.tsktab.get(p.name).add_up_link(link)
            elif p.kind is EndpointKind.DEVICE:
                self.msgmgr.add_device_link(link)
            elif p.direction == "terminal":
                self.terminals.setdefault(p.name, []).append(link)
        for j, p in enumerate(outs):
            link = self.link(t.name, p.name, LinkType.COMMAND, DEFAULT_COMMAND_PRIORITY,
                              EndpointKind.TASK, p.kind, t.machine, p.machine)
            link.src_port = j
            t.out_links.append(link)
        self._exception_wiring(t)
        self.host_link(t.name)  # made now so that every satellite numbers its links alike
        self.installs.append(req)
        self.changed("install", f"{t.name} on machine {t.machine} at level {t.level} "
                                 f"({len(ins)} in, {len(outs)} out)"
                      + (", standing" if t.standing else "")
                      + (f", restart={t.restart}" if t.restart != "never" else ""))
        if t.standing:
            self.msgmgr.start_standing(t, "started at install (standing task)")
        return t

    def link(self, src: str, dst: str, type: LinkType, prio: int, sk: EndpointKind,
              dk: EndpointKind, sm: int, dm: int, queued: int = 0, tap: bool = False) -> Link:
        mt = self.msgtab
        link = Link(mt.next_lid(), src, dst, type, prio, sk, dk, sm, dm, queued=queued, tap=tap)
        link.remote = dm >= 0 and not self.msgmgr.is_local(dm)
        mt.add(link)
        return link

    def _exception_wiring(self, t: TaskEntry) -> None:
        """The implicit links of a new task: exception taps and assassin links, both ways. Only
        exception and assassin tasks scan the table (they are linked to every lower task);
        an ordinary task meets the indexes of exception tasks (``msgmgr.taps``) and assassins
        (``self._assassins``), both in install order, so an install costs O(1) for them."""
        if t.role is Role.EXCEPTION:
            tap = TapPort()
            t.tap = tap
            links: dict[str, Link] = {}
            self.msgmgr.taps.append((t, tap, links))
            for u in self.tsktab:
                if u is not t and u.level < t.level:
                    links[u.name] = self.link(u.name, t.name, LinkType.SENSORY, TOP_PRIORITY,
                                               EndpointKind.TASK, EndpointKind.TASK, u.machine,
                                               t.machine, tap=True)
                    u.mark_tapped()
        for e, _tap, links in self.msgmgr.taps:
            if e is not t and e.level > t.level:
                links[t.name] = self.link(t.name, e.name, LinkType.SENSORY, TOP_PRIORITY,
                                           EndpointKind.TASK, EndpointKind.TASK, t.machine,
                                           e.machine, tap=True)
                t.mark_tapped()
        if t.role is Role.ASSASSIN:
            for u in self.tsktab:
                if u is not t and u.level < t.level \
                        and self.msgtab.get(t.name, u.name, LinkType.COMMAND) is None:
                    t.special_links[u.name] = self.link(
                        t.name, u.name, LinkType.COMMAND, TOP_PRIORITY, EndpointKind.TASK,
                        EndpointKind.TASK, t.machine, u.machine, tap=True)
        for a in self._assassins:
            if a.level > t.level:
                a.special_links[t.name] = self.link(
                    a.name, t.name, LinkType.COMMAND, TOP_PRIORITY, EndpointKind.TASK,
                    EndpointKind.TASK, a.machine, t.machine, tap=True)
        if t.role is Role.ASSASSIN:
            self._assassins.append(t)

    def host_link(self, task: str) -> Link:
        """The implicit command link from the host to ``task`` (made on first use). Raises
        InstallError if there is no such task."""
        link = self.host_links.get(task)
        if link is None:
            if task not in self.tsktab:
                raise InstallError(f"no task named {task!r}")
            t = self.tsktab.get(task)
            link = self.link("host", task, LinkType.COMMAND, DEFAULT_COMMAND_PRIORITY,
                              EndpointKind.HOST, EndpointKind.TASK, -1, t.machine, tap=True)
            self.host_links[task] = link
        return link

