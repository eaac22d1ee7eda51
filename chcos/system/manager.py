"""manager - the system manager (TSK0): boot, install, setpri and invoke, and the system map.

``install`` is :mod:`chcos.system.installer`'s (it checks everything first and changes nothing
unless all is well); the pacing of the map writes is :mod:`chcos.system.mapfile`'s. The system
manager gets its collaborators (kernel, tables, message manager, device table, setup) at
construction, as the narrow protocols of :mod:`chcos.system.ports`.

sysfile.map is written atomically soon after a change, never more often than its writes cost
allows (see :mod:`chcos.system.mapfile`); it records the tables, the devices and buses, and the
errors the system collected (``errors``: see :meth:`chcos.system.embedded.System.check`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from chcos.errors import ChcosError, InstallError, MessageError, TaskError
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
from chcos.system.installer import Installer, is_path
from chcos.system.mapfile import MAP_COST_FACTOR, MAP_MIN_GAP, MapFile
from chcos.system.ports import Devices, Messages, Scheduler, Setup
from chcos.tables.messages import (
    DEFAULT_COMMAND_PRIORITY,
    DEFAULT_SENSORY_PRIORITY,
    PRIORITIES,
    PRIORITY_TEXT,
    TOP_PRIORITY,
    EndpointKind,
    Link,
    LinkType,
    Msgtab,
)
from chcos.tables.tasks import TaskEntry, TaskFunc, Tsktab
from chcos.user.worldmodel import WorldModel

__all__ = ["MAP_COST_FACTOR", "MAP_MIN_GAP", "SystemManager", "is_path"]


class SystemManager:
    """TSK0 of a system: every table change goes through here."""

    def __init__(self, *, kernel: Scheduler, tsktab: Tsktab, msgtab: Msgtab, msgmgr: Messages,
                 devtab: Devices, setup: Setup) -> None:
        self.kernel = kernel
        self.tsktab = tsktab
        self.msgtab = msgtab
        self.msgmgr = msgmgr
        self.devtab = devtab
        self.setup = setup
        self.machines: set[int] = set()
        self.on_change: list[Callable[[str, str], None]] = []
        self.installer = Installer(tsktab=tsktab, msgtab=msgtab, msgmgr=msgmgr, devtab=devtab,
                                   setup=setup, machines=self.machines, changed=self._changed)
        self.map = MapFile(setup.map_path, self.map_doc, kernel.interrupt)
        # a device's health (status, cause, since) is part of the map: rewrite it on a change
        devtab.add_health_listener(lambda _d, _ok, _c: self.map_changed())
        kernel.add_idle_hook(self.map.on_idle)

    # ---- the installer's tables -------------------------------------------------------------
    @property
    def installs(self) -> list[Install]:
        """The install requests applied, in order."""
        return self.installer.installs

    @property
    def host_links(self) -> dict[str, Link]:
        """The implicit command link from the host to each task, by task name."""
        return self.installer.host_links

    @property
    def terminals(self) -> dict[str, list[Link]]:
        """The links fed by each terminal, by terminal name."""
        return self.installer.terminals

    def check_install(self, req: Install) -> tuple[TaskFunc, int, list[Any], list[Any]]:
        """Validate ``req`` without changing anything (see :meth:`Installer.check_install`).
        Raises InstallError listing every problem found."""
        return self.installer.check_install(req)

    def install(self, req: Install) -> TaskEntry:
        """Install a task (see :mod:`chcos.system.installer`). Raises InstallError (tables
        unchanged)."""
        return self.installer.install(req)

    def host_link(self, task: str) -> Link:
        """The implicit command link from the host to ``task`` (made on first use). Raises
        InstallError if there is no such task."""
        return self.installer.host_link(task)

    def _changed(self, kind: str, detail: str) -> None:
        self.msgmgr.event(kind, detail)
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
        if self.msgmgr.is_local(machine):
            self.setup.start_drivers([machine])
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
        mm = self.msgmgr
        if not mm.is_local(machine):
            self._changed("reload", f"machine {machine} reloaded from {sysfile} (remote)")
            return f"machine {machine} reloaded"
        tasks = [t for t in self.tsktab if t.machine == machine]
        for t in tasks:
            mm.wipe(t, f"machine {machine} reloaded from {sysfile}")
            factory = getattr(t.func, "world_model", None)
            t.world = factory() if callable(factory) else WorldModel()
        safe = 0
        for d in self.devtab:
            if not d.is_sensor and d.spec.machine == machine and d.spec.safe_value is not None:
                try:
                    self.devtab.write(d.name, d.spec.safe_value, source="reload")
                    safe += 1
                except ChcosError as exc:
                    mm.event("reload", f"safe value for {d.name} not written: {exc}")
        self._changed("reload", f"machine {machine} reloaded from scratch from {sysfile}: "
                                f"{len(tasks)} task(s) reset, {safe} actuator(s) safe")
        for t in tasks:
            if t.standing:
                mm.start_standing(t, "started after the reload")
        return f"machine {machine} reloaded from scratch ({len(tasks)} task(s))"

    # ---- setpri, invoke and task operations -------------------------------------------------
    def setpri(self, src: str, dst: str, priority: int) -> Link:
        """Set the priority of link ``src``/``dst`` now. Raises InstallError for an unknown link
        or a priority outside 0..99."""
        if priority not in PRIORITIES:
            raise InstallError(f"setpri {src} {dst}: priority {priority} outside {PRIORITY_TEXT}")
        try:
            link = self.msgtab.find(src, dst)
        except MessageError as exc:
            raise InstallError(f"setpri: {exc}") from exc
        old = link.priority
        self.msgmgr.setpri(link, priority)
        self._changed("setpri", f"{link.name} {old} -> {priority}")
        return link

    def default_priority(self, lk: Link) -> int:
        """The priority ``lk`` had when it was made (before any setpri)."""
        return (TOP_PRIORITY if lk.tap and lk.src != "host" else
                DEFAULT_COMMAND_PRIORITY if lk.type is LinkType.COMMAND else
                self.devtab.get(lk.src).spec.priority if lk.src_kind is EndpointKind.DEVICE
                else DEFAULT_SENSORY_PRIORITY)

    def resetpri_link(self, src: str, dst: str) -> Link:
        """``resetpri SRC DST``: link ``src``/``dst`` back to its default priority. Raises
        InstallError for an unknown link."""
        try:
            link = self.msgtab.find(src, dst)
        except MessageError as exc:
            raise InstallError(f"resetpri: {exc}") from exc
        return self.setpri(src, dst, self.default_priority(link))

    def invoke(self, task: str, command: Any = None, priority: int | None = None) -> str:
        """Send a command message from the host to ``task`` (at ``priority`` if given).
        Raises InstallError for an unknown task, Busy if it is held at a higher priority."""
        link = self.host_link(task)
        old = link.priority
        if priority is not None:
            if priority not in PRIORITIES:
                raise InstallError(f"invoke {task}: priority {priority} outside {PRIORITY_TEXT}")
            link.set_priority(priority)
        try:
            self.msgmgr.open(link, command, wait=False)
        except BaseException:
            link.set_priority(old)     # a refused invoke changes nothing, its priority neither
            raise
        args = (" " + " ".join(f"{k}={v}" for k, v in command.items())
                if isinstance(command, dict) else "" if command is None else f" {command!r}")
        self.msgmgr.event("invoke", f"host -> {task} at priority {link.priority}{args}")
        return f"{task} invoked at priority {link.priority}"

    def task_op(self, op: str, task: str) -> str:
        """Host ``suspend``, ``resume``, ``close``, ``resetpri`` or ``reset`` of ``task`` (or of
        a device, for suspend/resume: its readings are dropped and writes refused meanwhile).
        ``reset`` without a task resets every suspended task (see :meth:`reset`). Raises
        InstallError if unknown."""
        mm = self.msgmgr
        if op == "reset":
            return self.reset(task or None)
        if op in ("suspend", "resume") and task not in self.tsktab \
                and task in self.devtab:
            self.devtab.suspend(task) if op == "suspend" else self.devtab.resume(task)
            mm.event(op, f"host {op} device {task}")
            self.map_changed()
            return f"{task}: {op}"
        try:
            t = self.tsktab.get(task)
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
        mm = self.msgmgr
        if task is not None:
            try:
                top = self.tsktab.get(task)
            except TaskError as exc:
                raise InstallError(str(exc)) from exc
            todo = [t for t in self.tsktab if t is top or t.level < top.level]
        else:
            todo = list(self.tsktab)
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
                self.msgmgr.deliver(link, value)
            return f"{name} <- {value!r}"
        if name in self.devtab and self.devtab.get(name).is_sensor:
            if not (isinstance(value, bool) or (isinstance(value, int) and abs(value) < 2**63)
                    or (isinstance(value, float) and math.isfinite(value))):
                raise InstallError(f"inject {name}: {value!r} is not a reading; expected a "
                                   f"finite number (or true/false)")
            self.devtab.inject(name, value)
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
        tasks = []
        by_name = {r.name: r for r in self.installs}
        for t in self.tsktab:
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
        for lk in self.msgtab:
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
        } for d in self.devtab]
        return {"machines": sorted(self.machines), "devmaps": list(self.setup.devmaps),
                "base_dir": str(self.setup.base_dir),
                "task_path": [str(p) for p in self.setup.task_path],
                "time": self.kernel.clock.now(), "tasks": tasks, "links": links,
                "devices": devices, "buses": self.devtab.stats_doc(),
                "bus_status": self.devtab.bus_status(),
                "kernel": self.kernel.stats(), "errors": self.setup.errors()}

    # ---- the map file (see chcos.system.mapfile) --------------------------------------------
    @property
    def map_writes(self) -> int:
        """How many times sysfile.map was written."""
        return self.map.writes

    @property
    def map_clock(self) -> Callable[[], float]:
        """The clock that paces the map writes (monotonic; tests replace it)."""
        return self.map.clock

    @map_clock.setter
    def map_clock(self, clock: Callable[[], float]) -> None:
        self.map.clock = clock

    def save_map(self) -> None:
        """Write sysfile.map now (atomically) if the system has a map path; a failure raises
        nothing and is kept in ``self.map.error`` (see :mod:`chcos.system.mapfile`)."""
        self.map.save()

    def map_changed(self) -> None:
        """The tables changed: write sysfile.map now or soon (see :mod:`chcos.system.mapfile`;
        a failed write raises nothing)."""
        self.map.changed()

    def flush_map(self) -> None:
        """Write sysfile.map if a change is not written yet (a failure raises nothing: see
        ``self.map.error``)."""
        self.map.flush()
