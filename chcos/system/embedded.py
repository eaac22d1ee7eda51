"""embedded - one CHC-OS system in one process: the embedded default.

A :class:`System` is a satellite's kernel and tables (Tsktab, Msgtab, Devtab), its message and
system managers, its communications manager when it is one satellite of several, and the device
maps it was loaded from: the composition root, which builds every part through its constructor
and hands each its collaborators. In one process it hosts every machine (the embedded default);
:class:`chcos.satellites.satellite.Satellite` builds one for its machine with a link
``transport``. The host talks to it only through :meth:`System.execute` (command lines).

:meth:`System.check` raises what the system collected (interrupt handlers that failed, link
errors); :meth:`System.collected_errors` lists them (the map's ``errors``).
"""

from __future__ import annotations

import concurrent.futures
import logging
import threading
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, TypeVar

from chcos.comm.manager import CommManager
from chcos.comm.ports import LinkTransport
from chcos.devices.devtab import Devtab
from chcos.devices.spec import DeviceMap
from chcos.errors import ChcosError, KernelError
from chcos.kernel.clock import Clock, VirtualClock
from chcos.kernel.scheduler import Kernel
from chcos.messages.manager import MessageManager
from chcos.system import cmdline, sysmap
from chcos.system.manager import SystemManager
from chcos.system.ports import Setup
from chcos.tables.messages import Msgtab
from chcos.tables.tasks import TaskEntry, Tsktab
from chcos.user.context import TaskContext

log = logging.getLogger("chcos.system.embedded")
T = TypeVar("T")


class System:
    """A whole CHC-OS system in one process.

    ``devmaps`` are device-map files (loaded and validated together), or a ready
    :class:`DeviceMap`; ``machines`` are loaded at once (else use ``install -mN sysfile``);
    ``task_path`` lists directories where bare task names (``A1``) are found; ``base_dir``
    resolves relative file names in installs; ``map_path`` is where sysfile.map is written;
    ``local_machines`` are the machines this process runs (None: all of them, the embedded
    default; a satellite runs one and reaches the others through :mod:`chcos.comm.manager`);
    ``transport`` is that satellite's link (then ``local_machines`` is its one machine), on
    which it uses the keys under ``prefix``. Raises ConfigError for invalid device maps,
    BusError if a driver cannot start, KernelError for a transport without one local machine.
    """

    def __init__(self, devmaps: Sequence[str | Path] | DeviceMap = (), *,
                 clock: Clock | None = None, machines: Iterable[int] = (),
                 task_path: Sequence[str | Path] = (), base_dir: str | Path | None = None,
                 map_path: str | Path | None = None,
                 local_machines: Iterable[int] | None = None,
                 transport: LinkTransport | None = None, prefix: str = "chcos") -> None:
        # the composition root: every part gets its collaborators through its constructor
        local = set(local_machines) if local_machines is not None else None
        self.kernel = Kernel(clock)
        self.tsktab = Tsktab()
        self.msgtab = Msgtab()
        self.devtab = Devtab(self.kernel, local=local)
        if isinstance(devmaps, DeviceMap):
            self.devmap = devmaps
        elif devmaps:
            from chcos.devices.devmap import load

            self.devmap = load(list(devmaps))
        else:
            self.devmap = DeviceMap()
        self.devtab.load(self.devmap)
        self.task_path = [Path(p) for p in task_path]
        self.base_dir = Path(base_dir) if base_dir is not None else Path.cwd()
        self.map_path = Path(map_path) if map_path is not None else None
        # run state (learned world-model data) goes beside the map, never into the sources
        self.msgmgr = MessageManager(
            self.kernel, self.tsktab, self.msgtab, self.devtab, local=local,
            base_dir=self.base_dir,
            state_dir=self.map_path.parent if self.map_path is not None else self.base_dir)
        self.kernel.set_end_handler(self.msgmgr.activation_ended)
        self.devtab.listen(self.msgmgr)  # readings fan out over the links leaving the devices
        self.devtab.add_health_listener(self.msgmgr.device_health)
        # ---- the system and communications managers (issue 14: built here, with what they use)
        self.comm: CommManager | None = None
        if transport is not None:
            if self.msgmgr.local is None or len(self.msgmgr.local) != 1:
                raise KernelError("a System on a link runs exactly one machine: give "
                                  "local_machines={N}")
            (machine,) = self.msgmgr.local
            self.comm = CommManager(kernel=self.kernel, tsktab=self.tsktab, msgtab=self.msgtab,
                                    msgmgr=self.msgmgr, devtab=self.devtab, transport=transport,
                                    prefix=prefix, machine=machine)
            self.msgmgr.comm = self.comm    # the link replaces the one-process NoComm
            self.devtab.remote = self.comm  # actuators of other machines go over the link
        setup = Setup(task_path=self.task_path, base_dir=self.base_dir, map_path=self.map_path,
                      devmaps=list(self.devmap.files), start_drivers=self.start_drivers,
                      context=self._context, errors=self.collected_errors)
        self.sysmgr = SystemManager(kernel=self.kernel, tsktab=self.tsktab, msgtab=self.msgtab,
                                    msgmgr=self.msgmgr, devtab=self.devtab, setup=setup)
        self._thread: threading.Thread | None = None
        self._started_machines: set[int] = set()
        for m in machines:
            self.sysmgr.boot(m)

    def _context(self, task: TaskEntry) -> TaskContext:
        """The user context (thesis 6.1.2's user layer) of a newly installed task."""
        return TaskContext(task, self.kernel, self.msgmgr)

    # ---- collected errors -------------------------------------------------------------------
    def collected_errors(self) -> list[str]:
        """What this system collected and nobody raised yet, oldest first: interrupt handlers
        that failed (the kernel's) and link errors (the communications manager's)."""
        out = [f"kernel: {e}" for e in self.kernel.irq_errors]
        if self.comm is not None:
            out += [f"link: {e}" for e in self.comm.errors]
        return out

    def check(self) -> None:
        """Raise what the system collected, like canopen's ``Network.check()``: the kernel's
        (HandlerError, a KernelError: interrupt handlers and timer callbacks that failed, see
        :meth:`Kernel.check`), then the link's (LinkError: batches
        that could not be published, incoming messages refused). Nothing collected: returns."""
        self.kernel.check()
        if self.comm is not None:
            self.comm.check()

    # ---- devices ----------------------------------------------------------------------------
    def start_drivers(self, machines: Iterable[int]) -> None:
        """Start the bus drivers for the devices of ``machines`` not started yet."""
        new = set(machines) - self._started_machines
        if new:
            self.devtab.start_drivers(self.devmap, new)
            self._started_machines |= new

    # ---- host commands ----------------------------------------------------------------------
    def execute(self, line: str | cmdline.Request) -> str:
        """Carry out one host command (``install -m0i2o1 A1 S1 S2 M1``, ``setpri -9 A4 C1``,
        ``invoke C1``...) and return its answer. Thread-safe: while the kernel runs on another
        thread the command runs there, between task steps. Raises ChcosError (CommandSyntaxError,
        InstallError...) and leaves the tables unchanged on error."""
        req = cmdline.parse(line) if isinstance(line, str) else line
        if req is None:
            return ""
        if isinstance(req, cmdline.AxisCmd):
            return self._axis(req)
        return self.call(self.sysmgr.execute, req)

    def _axis(self, req: cmdline.AxisCmd) -> str:
        """The host's ``axis`` command (:func:`chcos.user.axes.operator_command`): waits here
        for the drive's confirmation, on this thread, while the kernel goes on. Raises
        KernelError when called on the kernel's own thread (it would wait for itself)."""
        from chcos.user.axes import OPERATOR_SLICE, operator_command

        kernel = self.kernel
        if kernel.running and kernel.on_kernel_thread():
            raise KernelError(f"axis {req.device}: an axis command waits for the drive and "
                              "cannot be given from the kernel's thread (a task uses ctx.axis)")

        def pump() -> None:     # a kernel nobody runs: run a slice of its time
            if not kernel.running:
                self.run_for(OPERATOR_SLICE)

        return operator_command(self.devtab, req.device, req.word, req.mode, pump)

    def call(self, fn: Callable[..., T], *args: Any) -> T:
        """Run ``fn(*args)`` on the kernel thread (between task steps) and return its result,
        or run it here if the kernel is not running on another thread. Exceptions propagate.
        Raises KernelError if the kernel does not get to it within 30 s."""
        if self.kernel.running and not self.kernel.on_kernel_thread():
            fut: concurrent.futures.Future[T] = concurrent.futures.Future()

            def job() -> None:
                try:
                    fut.set_result(fn(*args))
                except BaseException as exc:
                    fut.set_exception(exc)

            self.kernel.interrupt(job)
            try:
                return fut.result(timeout=30)
            except concurrent.futures.TimeoutError as exc:
                raise KernelError(f"kernel did not run {fn.__name__} within 30 s") from exc
        return fn(*args)

    def run_script(self, path: str | Path) -> list[str]:
        """Execute every line of a host script (such as the thesis' install script) in order.
        Raises ChcosError naming the file and line of the first failing command."""
        answers = []
        lines = Path(path).read_text(encoding="utf-8").splitlines()
        for no, line in enumerate(lines, 1):
            try:
                ans = self.execute(line)
            except ChcosError as exc:
                raise type(exc)(f"{path}:{no}: {line.strip()}: {exc}") from exc
            if ans:
                answers.append(ans)
        self.call(self.sysmgr.flush_map)  # one map write for the script's last changes
        return answers

    def nmt(self, command: str, node: int, bus: str = "") -> str:
        """Send NMT ``command`` (start, stop, preop, reset, reset-comm) to CANopen node
        ``node`` (of ``bus`` if given): the host's ``nmt`` command as a Python call, logged as
        it is (see :meth:`SystemManager.nmt`); on the kernel thread. Raises CommandSyntaxError
        for a command that is none or a node id outside 1..127, InstallError for a node no
        bus has, BusError when it cannot be sent."""
        return self.execute(cmdline.NmtCmd(*self._nmt_args(command, node), bus))

    @staticmethod
    def _nmt_args(command: str, node: int) -> tuple[str, int]:
        req = cmdline.parse(["nmt", command, str(node)])
        assert isinstance(req, cmdline.NmtCmd)
        return req.word, req.node

    def invoke(self, task: str, command: Any = None, priority: int | None = None) -> str:
        """Send a command message from the host to ``task`` (see SystemManager.invoke)."""
        return self.sysmgr.invoke(task, command, priority)

    # ---- running ----------------------------------------------------------------------------
    def run(self, until: float | None = None) -> None:
        """Run the kernel on this thread until ``until`` (clock time) or until stopped; on a
        virtual clock also until nothing more can happen. Then writes the map's pending
        changes (see :meth:`SystemManager.map_changed`)."""
        self.kernel.run(until)
        self.sysmgr.flush_map()

    def run_for(self, seconds: float) -> None:
        """Run for ``seconds`` of clock time from now (see :meth:`run`)."""
        self.run(self.kernel.clock.now() + seconds)

    def start(self) -> None:
        """Run the kernel on a background thread (for interactive use). Raises KernelError if
        it already runs."""
        if self._thread is not None:
            raise KernelError("system already started")
        self._thread = threading.Thread(target=self.kernel.run, name="chcos-kernel", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the kernel (and join its background thread)."""
        self.kernel.stop()
        if self._thread is not None:
            self._thread.join(timeout=10)
            self._thread = None

    def shutdown(self) -> None:
        """Stop, write safe values to every actuator, stop the drivers, close output files."""
        self.stop()
        self._end_activations()
        self.devtab.stop_drivers()
        self._end_activations()     # one restarted in the shutdown window never ran
        self.msgmgr.close_files()
        try:  # the map's runtime fields as they were at the end
            self.sysmgr.save_map()
        except OSError:
            log.exception("cannot write the system map at shutdown")

    def _end_activations(self) -> None:
        """Close every task's activation (runs its finally blocks)."""
        for t in self.tsktab:
            if t.coro is not None:
                t.coro.close()
                t.coro = None

    def __enter__(self) -> System:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    # ---- rebuilding -------------------------------------------------------------------------
    @classmethod
    def from_map(cls, path: str | Path, *, clock: Clock | None = None,
                 map_path: str | Path | None = None) -> System:
        """Rebuild a system from its sysfile.map (machines, device maps, installs in order,
        priorities). Raises ConfigError for a bad map, InstallError if an install fails."""
        doc = sysmap.read(path)
        system = cls(doc.get("devmaps", []), clock=clock or VirtualClock(),
                     task_path=doc.get("task_path", []), base_dir=doc.get("base_dir"),
                     map_path=map_path)
        for line in sysmap.install_lines(doc):
            system.execute(line)
        system.sysmgr.flush_map()
        return system
