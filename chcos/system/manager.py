"""manager - the system manager (TSK0): install, setpri and invoke, and the system map.

``install`` places a task on a machine with its input sources and output destinations. It checks
everything first and changes nothing unless all is well: the name is new (tasks are never removed),
the machine is loaded, every peer exists and is of the right kind (sensory inputs come from sensors,
files, terminals or tasks; command outputs go to actuators, files or tasks), at most eight of each,
and every link keeps the hierarchy: sensory links go to a strictly higher level, command links to a
strictly lower one (levels follow from the links, or ``--level`` places a task higher). Then it
enters the task, its links and ports, the exception taps and assassin links, and marks
sysfile.map for writing.

sysfile.map is written atomically after a change, at most every MAP_MIN_GAP seconds (and at
least MAP_COST_FACTOR write-durations apart, so a burst of N installs costs O(N), not O(N²));
the change still unwritten is written when the script ends, when the kernel goes idle or
``run`` returns, on ``map`` and at shutdown, or by a timer MAP_MIN_GAP later. A crash can
therefore lose the last fraction of a second of changes, never leave a map that does not
rebuild a system: every map on disk is a whole one (temporary file, fsync, rename).
"""

from __future__ import annotations

import math
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from chcos.errors import ChcosError, InstallError, MessageError, TaskError
from chcos.system import sysmap
from chcos.system.cmdline import (
    Boot,
    Inject,
    Install,
    Invoke,
    Request,
    ResetPri,
    SetPri,
    ShowMap,
    TaskOp,
)
from chcos.system.loader import resolve
from chcos.tables.messages import (
    DEFAULT_COMMAND_PRIORITY,
    DEFAULT_SENSORY_PRIORITY,
    PORTS,
    PRIORITIES,
    PRIORITY_TEXT,
    TOP_PRIORITY,
    EndpointKind,
    InPort,
    Link,
    LinkType,
    TapPort,
)
from chcos.tables.tasks import Role, TaskEntry, TaskFunc
from chcos.user.context import TaskContext
from chcos.user.worldmodel import WorldModel

if TYPE_CHECKING:
    from chcos.system.embedded import System

_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_.-]*")
MAP_MIN_GAP = 0.25      # seconds between two sysfile.map writes during a burst of changes
MAP_COST_FACTOR = 10.0  # ... and at least this many times the last write's duration


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


class SystemManager:
    """TSK0 of a system: every table change goes through here."""

    def __init__(self, system: System) -> None:
        self.sys = system
        self.machines: set[int] = set()
        self.installs: list[Install] = []
        self.host_links: dict[str, Link] = {}
        self.terminals: dict[str, list[Link]] = {}
        self.on_change: list[Callable[[str, str], None]] = []
        self._assassins: list[TaskEntry] = []   # in install order (see _exception_wiring)
        self.map_clock: Callable[[], float] = time.monotonic  # paces the map writes
        self.map_writes = 0
        self._map_dirty = False
        self._map_next = 0.0
        self._map_timer: threading.Timer | None = None
        # a device's health (status, cause, since) is part of the map: rewrite it on a change
        system.devtab.add_health_listener(lambda _d, _ok, _c: self.map_changed())
        system.kernel.add_idle_hook(self._map_idle)

    # ---- helpers ----------------------------------------------------------------------------
    def _path(self, name: str) -> Path:
        return self.sys.msgmgr.resolve_path(name)

    def _peer(self, name: str) -> _Peer | None:
        s = self.sys
        if name in s.tsktab:
            t = s.tsktab.get(name)
            return _Peer(name, EndpointKind.TASK, t.level, t.machine)
        if name in s.devtab:
            d = s.devtab.get(name).spec
            return _Peer(name, EndpointKind.DEVICE, 0, d.machine, d.direction)
        if name.startswith(("/dev/tty", "/dev/pts/")):
            return _Peer(name, EndpointKind.FILE, 0, -1, "terminal")
        if is_path(name):
            return _Peer(name, EndpointKind.FILE, 0, -1, "file")
        return None

    def _changed(self, kind: str, detail: str) -> None:
        self.sys.msgmgr.event(kind, detail)
        self.map_changed()
        for hook in self.on_change:
            hook(kind, detail)

    # ---- boot -------------------------------------------------------------------------------
    def boot(self, machine: int, sysfile: str = "sysfile") -> str:
        """Load machine ``machine`` (``install -mN sysfile``): start the drivers of its devices.
        Loading a loaded machine again reloads it from scratch (thesis 6.3, see :meth:`reload`).
        Raises BusError if a driver cannot start."""
        if machine in self.machines:
            return self.reload(machine, sysfile)
        if self.sys.msgmgr.is_local(machine):
            self.sys.start_drivers([machine])
        self.machines.add(machine)
        self._changed("boot", f"machine {machine} loaded from {sysfile}")
        return f"machine {machine} loaded"

    def reload(self, machine: int, sysfile: str = "sysfile") -> str:
        """A second ``install -mN sysfile``: "the satellite is to be reloaded from scratch"
        (thesis 6.3). Every task of the machine loses its activation (its owner is told it was
        pre-empted), its ownership, wait queue, unread messages, world model and suspension;
        whatever it owned is released; the machine's actuators go to their safe values; then its
        standing tasks start again as at install. The tables (tasks, links, priorities) and the
        bus drivers stay: they are the configuration the satellite is loaded with."""
        s = self.sys
        mm = s.msgmgr
        if not mm.is_local(machine):
            self._changed("reload", f"machine {machine} reloaded from {sysfile} (remote)")
            return f"machine {machine} reloaded"
        tasks = [t for t in s.tsktab if t.machine == machine]
        for t in tasks:
            mm.wipe(t, f"machine {machine} reloaded from {sysfile}")
            factory = getattr(t.func, "world_model", None)
            t.world = factory() if callable(factory) else WorldModel()
        safe = 0
        for d in s.devtab:
            if not d.is_sensor and d.spec.machine == machine and d.spec.safe_value is not None:
                try:
                    s.devtab.write(d.name, d.spec.safe_value, source="reload")
                    safe += 1
                except ChcosError as exc:
                    mm.event("reload", f"safe value for {d.name} not written: {exc}")
        self._changed("reload", f"machine {machine} reloaded from scratch from {sysfile}: "
                                f"{len(tasks)} task(s) reset, {safe} actuator(s) safe")
        for t in tasks:
            if t.standing:
                mm.start_standing(t, "started after the reload")
        return f"machine {machine} reloaded from scratch ({len(tasks)} task(s))"

    # ---- install ----------------------------------------------------------------------------
    def check_install(self, req: Install) -> tuple[TaskFunc, int, list[_Peer], list[_Peer]]:
        """Validate ``req`` without changing anything; returns (function, level, inputs,
        outputs). Raises InstallError listing every problem found."""
        errs: list[str] = []
        s = self.sys
        if not _NAME.fullmatch(req.name):
            errs.append(f"task name {req.name!r} is not a valid name (letters, digits, _ . -)")
        elif req.name in s.tsktab:
            t = s.tsktab.get(req.name)
            errs.append(f"task {req.name} is already installed on machine {t.machine} "
                        "(tasks are never removed or replaced)")
        elif req.name in s.devtab:
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
        if not self.sys.msgmgr.is_local(req.machine):
            func = _elsewhere  # its own satellite loads the code
        else:
            try:
                func = resolve(req.code or req.name, self.sys.task_path)
            except InstallError as exc:
                errs.append(str(exc))
        if errs or func is None:
            raise InstallError(f"install {req.name} refused, tables unchanged:\n  - "
                               + "\n  - ".join(errs))
        return func, level, ins, outs

    def install(self, req: Install) -> TaskEntry:
        """Install a task (see the module doc). Raises InstallError (tables unchanged)."""
        func, level, ins, outs = self.check_install(req)
        s = self.sys
        role = Role(req.role)
        if getattr(func, "chcos_system_driver", False):
            role = Role.SYSTEM
        t = TaskEntry(tid=s.tsktab.next_tid(), name=req.name, machine=req.machine, level=level,
                      func=func, code=req.code, role=role, params=dict(req.params))
        factory = getattr(func, "world_model", None)
        t.world = factory() if callable(factory) else WorldModel()
        t.ctx = TaskContext(t, s.kernel, s.msgmgr)
        t.prio = t.default_prio = DEFAULT_COMMAND_PRIORITY
        t.standing, t.restart, t.backoff = req.standing, req.restart, req.backoff
        s.tsktab.add(t)
        for i, p in enumerate(ins):
            prio = (s.devtab.get(p.name).spec.priority if p.kind is EndpointKind.DEVICE
                    else DEFAULT_SENSORY_PRIORITY)
            link = self._link(p.name, t.name, LinkType.SENSORY, prio, p.kind, EndpointKind.TASK,
                              p.machine, t.machine, queued=req.queued.get(p.name, 0))
            link.dst_port = i
            port = InPort(link, i)
            link.port = port
            t.in_ports.append(port)
            if p.kind is EndpointKind.TASK:
                s.tsktab.get(p.name).up_links.append(link)
            elif p.kind is EndpointKind.DEVICE:
                s.msgmgr.add_device_link(link)
            elif p.direction == "terminal":
                self.terminals.setdefault(p.name, []).append(link)
        for j, p in enumerate(outs):
            link = self._link(t.name, p.name, LinkType.COMMAND, DEFAULT_COMMAND_PRIORITY,
                              EndpointKind.TASK, p.kind, t.machine, p.machine)
            link.src_port = j
            t.out_links.append(link)
        self._exception_wiring(t)
        self.host_link(t.name)  # made now so that every satellite numbers its links alike
        self.installs.append(req)
        self._changed("install", f"{t.name} on machine {t.machine} at level {t.level} "
                                 f"({len(ins)} in, {len(outs)} out)"
                      + (", standing" if t.standing else "")
                      + (f", restart={t.restart}" if t.restart != "never" else ""))
        if t.standing:
            s.msgmgr.start_standing(t, "started at install (standing task)")
        return t

    def _link(self, src: str, dst: str, type: LinkType, prio: int, sk: EndpointKind,
              dk: EndpointKind, sm: int, dm: int, queued: int = 0, tap: bool = False) -> Link:
        mt = self.sys.msgtab
        link = Link(mt.next_lid(), src, dst, type, prio, sk, dk, sm, dm, queued=queued, tap=tap)
        link.remote = dm >= 0 and not self.sys.msgmgr.is_local(dm)
        mt.add(link)
        return link

    def _exception_wiring(self, t: TaskEntry) -> None:
        """The implicit links of a new task: exception taps and assassin links, both ways. Only
        exception and assassin tasks scan the table (they are linked to every lower task);
        an ordinary task meets the indexes of exception tasks (``msgmgr.taps``) and assassins
        (``self._assassins``), both in install order, so an install costs O(1) for them."""
        s = self.sys
        if t.role is Role.EXCEPTION:
            tap = TapPort()
            t.tap = tap
            links: dict[str, Link] = {}
            s.msgmgr.taps.append((t, tap, links))
            for u in s.tsktab:
                if u is not t and u.level < t.level:
                    links[u.name] = self._link(u.name, t.name, LinkType.SENSORY, TOP_PRIORITY,
                                               EndpointKind.TASK, EndpointKind.TASK, u.machine,
                                               t.machine, tap=True)
        for e, _tap, links in s.msgmgr.taps:
            if e is not t and e.level > t.level:
                links[t.name] = self._link(t.name, e.name, LinkType.SENSORY, TOP_PRIORITY,
                                           EndpointKind.TASK, EndpointKind.TASK, t.machine,
                                           e.machine, tap=True)
        if t.role is Role.ASSASSIN:
            for u in s.tsktab:
                if u is not t and u.level < t.level \
                        and s.msgtab.get(t.name, u.name, LinkType.COMMAND) is None:
                    t.special_links[u.name] = self._link(
                        t.name, u.name, LinkType.COMMAND, TOP_PRIORITY, EndpointKind.TASK,
                        EndpointKind.TASK, t.machine, u.machine, tap=True)
        for a in self._assassins:
            if a.level > t.level:
                a.special_links[t.name] = self._link(
                    a.name, t.name, LinkType.COMMAND, TOP_PRIORITY, EndpointKind.TASK,
                    EndpointKind.TASK, a.machine, t.machine, tap=True)
        if t.role is Role.ASSASSIN:
            self._assassins.append(t)

    # ---- setpri, invoke and task operations -------------------------------------------------
    def setpri(self, src: str, dst: str, priority: int) -> Link:
        """Set the priority of link ``src``/``dst`` now. Raises InstallError for an unknown link
        or a priority outside 0..99."""
        if priority not in PRIORITIES:
            raise InstallError(f"setpri {src} {dst}: priority {priority} outside {PRIORITY_TEXT}")
        try:
            link = self.sys.msgtab.find(src, dst)
        except MessageError as exc:
            raise InstallError(f"setpri: {exc}") from exc
        old = link.priority
        self.sys.msgmgr.setpri(link, priority)
        self._changed("setpri", f"{link.name} {old} -> {priority}")
        return link

    def default_priority(self, lk: Link) -> int:
        """The priority ``lk`` had when it was made (before any setpri)."""
        s = self.sys
        return (TOP_PRIORITY if lk.tap and lk.src != "host" else
                DEFAULT_COMMAND_PRIORITY if lk.type is LinkType.COMMAND else
                s.devtab.get(lk.src).spec.priority if lk.src_kind is EndpointKind.DEVICE
                else DEFAULT_SENSORY_PRIORITY)

    def resetpri_link(self, src: str, dst: str) -> Link:
        """``resetpri SRC DST``: link ``src``/``dst`` back to its default priority. Raises
        InstallError for an unknown link."""
        try:
            link = self.sys.msgtab.find(src, dst)
        except MessageError as exc:
            raise InstallError(f"resetpri: {exc}") from exc
        return self.setpri(src, dst, self.default_priority(link))

    def host_link(self, task: str) -> Link:
        """The implicit command link from the host to ``task`` (made on first use). Raises
        InstallError if there is no such task."""
        link = self.host_links.get(task)
        if link is None:
            if task not in self.sys.tsktab:
                raise InstallError(f"no task named {task!r}")
            t = self.sys.tsktab.get(task)
            link = self._link("host", task, LinkType.COMMAND, DEFAULT_COMMAND_PRIORITY,
                              EndpointKind.HOST, EndpointKind.TASK, -1, t.machine, tap=True)
            self.host_links[task] = link
        return link

    def invoke(self, task: str, command: Any = None, priority: int | None = None) -> str:
        """Send a command message from the host to ``task`` (at ``priority`` if given).
        Raises InstallError for an unknown task, Busy if it is held at a higher priority."""
        link = self.host_link(task)
        old = link.priority
        if priority is not None:
            if priority not in PRIORITIES:
                raise InstallError(f"invoke {task}: priority {priority} outside {PRIORITY_TEXT}")
            link.priority = priority
        try:
            self.sys.msgmgr.open(link, command, wait=False)
        except BaseException:
            link.priority = old        # a refused invoke changes nothing, its priority neither
            raise
        args = (" " + " ".join(f"{k}={v}" for k, v in command.items())
                if isinstance(command, dict) else "" if command is None else f" {command!r}")
        self.sys.msgmgr.event("invoke", f"host -> {task} at priority {link.priority}{args}")
        return f"{task} invoked at priority {link.priority}"

    def task_op(self, op: str, task: str) -> str:
        """Host ``suspend``, ``resume``, ``close``, ``resetpri`` or ``reset`` of ``task`` (or of
        a device, for suspend/resume: its readings are dropped and writes refused meanwhile).
        ``reset`` without a task resets every suspended task (see :meth:`reset`). Raises
        InstallError if unknown."""
        mm = self.sys.msgmgr
        if op == "reset":
            return self.reset(task or None)
        if op in ("suspend", "resume") and task not in self.sys.tsktab \
                and task in self.sys.devtab:
            self.sys.devtab.suspend(task) if op == "suspend" else self.sys.devtab.resume(task)
            mm.event(op, f"host {op} device {task}")
            self.map_changed()
            return f"{task}: {op}"
        try:
            t = self.sys.tsktab.get(task)
        except TaskError as exc:
            raise InstallError(str(exc)) from exc
        if op == "suspend":
            mm.suspend_task(t, "the host")
        elif op == "resume":
            mm.resume_task(t)
        elif op == "resetpri":
            prio = mm.resetpri(t)
            mm.event("resetpri", f"host resetpri {task}: priority {prio}")
            return f"{task}: priority {prio}"
        else:
            mm.close(self.host_link(task))
        mm.event(op, f"host {op} {task}")
        self.map_changed()
        return f"{task}: {op}"

    def reset(self, task: str | None = None) -> str:
        """The operator's acknowledgement after an emergency: every suspended task (below and
        including ``task`` if given) has its activation ended, is resumed unowned at its
        default priority (standing tasks re-arm themselves), and every link raised by setpri
        keeps its priority. Nothing is commanded: the job is started again by an ``invoke``.
        Raises InstallError for an unknown task."""
        mm = self.sys.msgmgr
        if task is not None:
            try:
                top = self.sys.tsktab.get(task)
            except TaskError as exc:
                raise InstallError(str(exc)) from exc
            todo = [t for t in self.sys.tsktab if t is top or t.level < top.level]
        else:
            todo = list(self.sys.tsktab)
        done = [t.name for t in todo if mm.is_local(t.machine) and t.frozen and mm.reset_task(t)]
        mm.event("reset", f"host reset: {', '.join(done) or 'nothing was suspended'}")
        self.map_changed()
        return f"reset: {', '.join(done) or 'nothing was suspended'}"

    def inject(self, name: str, value: Any) -> str:
        """Feed ``value`` to sensor or terminal ``name`` (as an interrupt would). Raises
        InstallError if there is no such sensor or terminal, or if a sensor's value is not a
        finite number or a boolean (nan, inf, strings, lists are refused)."""
        if name in self.terminals:
            for link in self.terminals[name]:
                self.sys.msgmgr.deliver(link, value)
            return f"{name} <- {value!r}"
        if name in self.sys.devtab and self.sys.devtab.get(name).is_sensor:
            if not (isinstance(value, bool) or (isinstance(value, int) and abs(value) < 2**63)
                    or (isinstance(value, float) and math.isfinite(value))):
                raise InstallError(f"inject {name}: {value!r} is not a reading; expected a "
                                   f"finite number (or true/false)")
            self.sys.devtab.inject(name, value)
            return f"{name} <- {value!r}"
        raise InstallError(f"inject: no sensor or terminal named {name!r}")

    # ---- dispatch and map -------------------------------------------------------------------
    def execute(self, req: Request) -> str:
        """Carry out one parsed host request; returns a one-line answer. Raises ChcosError."""
        if isinstance(req, Boot):
            return self.boot(req.machine, req.sysfile)
        if isinstance(req, Install):
            t = self.install(req)
            return f"installed {t.name} on machine {t.machine} at level {t.level}"
        if isinstance(req, SetPri):
            link = self.setpri(req.src, req.dst, req.priority)
            return f"{link.name} priority {link.priority}"
        if isinstance(req, ResetPri):
            link = self.resetpri_link(req.src, req.dst)
            return f"{link.name} priority {link.priority}"
        if isinstance(req, Invoke):
            return self.invoke(req.task, req.command or None, req.priority)
        if isinstance(req, TaskOp):
            return self.task_op(req.op, req.task)
        if isinstance(req, Inject):
            return self.inject(req.device, req.value)
        if isinstance(req, ShowMap):
            from chcos.system.textview import render_text

            self.save_map()
            return render_text(self.map_doc())
        raise ChcosError(f"unknown request {req!r}")

    def map_doc(self) -> dict[str, Any]:
        """The system map as a JSON-ready dict (see :mod:`chcos.system.sysmap`)."""
        s = self.sys
        tasks = []
        by_name = {r.name: r for r in self.installs}
        for t in s.tsktab:
            r = by_name[t.name]
            tasks.append({
                "name": t.name, "machine": t.machine, "level": t.level,
                "level_given": r.level is not None, "code": t.code, "role": r.role,
                "inputs": list(r.inputs), "outputs": list(r.outputs), "params": dict(r.params),
                "queued": dict(r.queued), "standing": r.standing, "restart": r.restart,
                "backoff": r.backoff, "restarts": t.restarts,
                "frozen": t.frozen, "status": t.state.value,
                "owner": t.owner.src if t.owner is not None else None, "priority": t.prio,
                "steps": t.steps, "activations": t.activations, "completions": t.completions,
                "abnormal": t.abnormal, "last_error": t.last_error,
                "world": t.world.snapshot() if t.world is not None else {},
            })
        links = []
        for lk in s.msgtab:
            default = self.default_priority(lk)
            links.append({
                "src": lk.src, "dst": lk.dst, "type": lk.type.value, "priority": lk.priority,
                "default_priority": default, "status": lk.status.value, "queued": lk.queued,
                "implicit": lk.tap, "sent": lk.sent, "overwritten": lk.overwritten,
                "delivered": lk.delivered,
            })
        devices = [{
            "name": d.name, "direction": d.spec.direction, "machine": d.spec.machine,
            "bus": d.spec.bus, "status": d.status.value, "value": d.value,
            "readings": d.readings, "overwrites": d.overwrites, "units": d.spec.units,
            "commands": d.commands, "reason": d.reason, "since": d.since,
            "updated_at": d.updated_at,
            "pending": d.pending, "write_errors": d.write_errors,
            "last_write_error": d.last_write_error,
        } for d in s.devtab]
        return {"machines": sorted(self.machines), "devmaps": list(s.devmap.files),
                "base_dir": str(s.base_dir), "task_path": [str(p) for p in s.task_path],
                "time": s.kernel.clock.now(), "tasks": tasks, "links": links,
                "devices": devices, "buses": s.devtab.stats_doc()}

    def save_map(self) -> None:
        """Write sysfile.map now (atomically) if the system has a map path. Raises OSError if
        it cannot be written."""
        if self.sys.map_path is None:
            return
        t0 = self.map_clock()
        sysmap.write(self.sys.map_path, self.map_doc())
        self._map_dirty = False   # only once written: a failed write is tried again
        self.map_writes += 1
        t1 = self.map_clock()
        self._map_next = t1 + max(MAP_MIN_GAP, MAP_COST_FACTOR * (t1 - t0))

    def map_changed(self) -> None:
        """The tables changed: write sysfile.map now if the last write is long enough ago (see
        the module doc), else leave it to :meth:`flush_map` (end of a script or run, an idle
        kernel, a timer). Raises OSError if a write due now fails."""
        if self.sys.map_path is None:
            return
        self._map_dirty = True
        if self.map_clock() >= self._map_next:
            self.save_map()
        elif self._map_timer is None:
            delay = max(0.0, self._map_next - self.map_clock())
            timer = threading.Timer(delay, self.sys.kernel.interrupt, (self._map_timed,))
            timer.daemon = True
            self._map_timer = timer
            timer.start()

    def flush_map(self) -> None:
        """Write sysfile.map if a change is not written yet. Raises OSError if it cannot be
        written."""
        if self._map_dirty:
            self.save_map()

    def _map_timed(self) -> None:
        """The timer armed by :meth:`map_changed`, run on the kernel thread: writes what
        waits (or arms itself again if it fired a little early)."""
        self._map_timer = None
        if self._map_dirty:
            self.map_changed()

    def _map_idle(self) -> None:
        """Idle hook: write the map if a change waits and its time has come."""
        if self._map_dirty and self.map_clock() >= self._map_next:
            self.save_map()
