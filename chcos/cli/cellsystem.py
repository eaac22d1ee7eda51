"""cellsystem - the system a user's system file describes, built and running in one process.

:func:`open_cell` builds it (:mod:`chcos.satellites.sysfile`: device maps, task path, install
script), every machine in it: on real time against the buses the maps name
(:class:`SinceStartClock`), or on virtual time against simulated slaves generated from the maps
(:mod:`chcos.apps.sim.from_map`). With ``outputs=False`` actuator writes are logged and never
reach a driver (:class:`OutputsOff`: commissioning a live bus without driving anything).
:class:`Cell` is the running cell: its devices, messages, a snapshot, and a close that puts
every actuator at its safe value. ``chcos run SYSTEM`` (:mod:`chcos.cli.cellrun`) and
``chcos monitor`` use it; so does :mod:`chcos.testing`.
"""

from __future__ import annotations

import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from chcos.devices.devmap import load
from chcos.devices.driver import Driver
from chcos.devices.entry import DeviceEntry
from chcos.errors import ConfigError
from chcos.kernel.clock import Clock, RealClock, VirtualClock
from chcos.kernel.instrument import Counters
from chcos.satellites import sysfile
from chcos.system.embedded import System

if TYPE_CHECKING:   # the simulators' bus libraries load only for a virtual run (open_cell)
    from chcos.apps.sim.from_map import Plant, SimSlaves


class SinceStartClock(RealClock):
    """Wall-clock time counted from the clock's creation, so every time a user sees (progress,
    ``map``, events) reads as seconds since the start, not the machine's uptime. Only for a
    system in one process: satellites keep :class:`RealClock`, whose times agree across
    processes."""

    def __init__(self) -> None:
        self.origin = time.monotonic()

    def now(self) -> float:
        """Seconds since this clock was made."""
        return time.monotonic() - self.origin

    def idle(self, wake: threading.Event, deadline: float | None) -> None:
        """Wait on ``wake`` until the deadline (or forever if there is none)."""
        if deadline is None:
            wake.wait()
        else:
            delay = deadline - self.now()
            if delay > 0:
                wake.wait(delay)


class OutputsOff(Driver):
    """Stands in for an actuator's driver when outputs are off: every write is logged (clock
    time since the start, device, raw value) and goes nowhere. The real driver keeps reading
    the bus's sensors."""

    kind = "outputs-off"

    def __init__(self, inner: Driver, log: Callable[[str, Any], None]) -> None:
        super().__init__(inner.bus, list(inner.devices.values()), inner.host)
        self.inner = inner
        self.sent_frames = inner.sent_frames    # what the wrapped driver still sends itself
        self._log = log
        self._running = True        # stands in for a driver that is already running

    def start(self) -> None:
        """Nothing to open: the wrapped driver is already running."""

    def check_value(self, device: str, value: Any) -> str | None:
        """The wrapped driver's check: with outputs off a command is refused as it would be
        with them on."""
        return self.inner.check_value(device, value)

    def accepts(self, device: str) -> tuple[float, float, bool] | None:
        """The wrapped driver's (see :meth:`check_value`)."""
        return self.inner.accepts(device)

    def _write(self, device: str, value: Any) -> None:
        """Log the write instead of sending it."""
        self._log(device, value)

    def stop(self) -> None:
        """Nothing to close: Devtab stops the wrapped driver."""

    def settle(self, timeout: float) -> bool:
        """Nothing is ever outstanding here."""
        return True


class CellSystem(System):
    """A :class:`System` whose actuator writes can be switched off at the drivers
    (``outputs=False``): see :class:`OutputsOff`."""

    def __init__(self, *args: Any, outputs: bool = True,
                 on_output: Callable[[str, Any], None] | None = None, **kw: Any) -> None:
        self.outputs = outputs
        self._on_output = on_output or (lambda device, value: None)
        super().__init__(*args, **kw)

    def start_drivers(self, machines: Iterable[int]) -> None:
        """Start the drivers; with outputs off, put an :class:`OutputsOff` in front of every
        actuator."""
        super().start_drivers(machines)
        if self.outputs:
            return
        for e in self.devtab:
            if not e.is_sensor and e.driver is not None and not isinstance(e.driver,
                                                                           OutputsOff):
                e.driver = OutputsOff(e.driver, self._on_output)


@dataclass
class Cell:
    """A user's system, built and installed; see :func:`open_cell`."""

    sf: sysfile.SystemFile
    system: CellSystem
    counters: Counters
    slaves: SimSlaves | None
    virtual: bool
    start: float = 0.0
    answers: list[str] = field(default_factory=list)
    outputs_log: list[tuple[float, str, Any]] = field(default_factory=list)
    closed: bool = False

    def now(self) -> float:
        """Seconds of clock time since the start of the run."""
        return self.system.kernel.clock.now() - self.start

    def run_for(self, seconds: float) -> None:
        """Run ``seconds`` of clock time (virtual time: as fast as possible)."""
        self.system.run_for(seconds)

    def device(self, name: str) -> DeviceEntry:
        """The Devtab entry of device ``name``; raises DeviceError if there is none."""
        return self.system.devtab.get(name)

    def messages(self) -> int:
        """Messages sent on every link so far."""
        return sum(lk.sent for lk in self.system.msgtab)

    def snapshot(self) -> dict[str, Any]:
        """Devices, tasks and counters as plain data (call on the kernel thread or while the
        kernel is stopped; :meth:`System.call` does that)."""
        now = self.system.kernel.clock.now()
        devices = [{"name": e.name, "direction": e.spec.direction, "value": e.value,
                    "units": e.spec.units, "status": e.status.value, "reason": e.reason,
                    "age": None if e.updated_at is None else now - e.updated_at,
                    "readings": e.readings, "commands": e.commands, "rejected": e.rejected,
                    "driven": e.driver is not None}
                   for e in self.system.devtab]
        tasks = [{"name": t.name, "level": t.level, "machine": t.machine,
                  "state": t.state.value, "steps": t.steps, "completions": t.completions,
                  "abnormal": t.abnormal, "error": t.last_error}
                 for t in self.system.tsktab]
        return {"t": now - self.start, "devices": devices, "tasks": tasks,
                "messages": self.messages(),
                "bus_errors": dict(self.system.devtab.last_bus_error),
                "bus_error_count": sum(self.system.devtab.bus_errors.values())}

    def close(self) -> None:
        """Stop the kernel, put every actuator at its safe value (what each driver confirmed is
        in the device table's ``safe_outcomes``), stop the drivers and the simulated slaves.
        Idempotent."""
        if self.closed:
            return
        self.closed = True
        self.system.stop()
        try:
            self.system.shutdown()
        finally:
            if self.slaves is not None:
                self.slaves.close()


def _boot_lines(sf: sysfile.SystemFile, machines: Iterable[int]) -> list[str]:
    return [f"install -m{m} sysfile" for m in sorted(set(machines))]


@contextmanager
def open_cell(system_file: str | Path, *, virtual: bool = False, outputs: bool = True,
              workdir: str | Path | None = None, clock: Clock | None = None,
              quiet_slaves: bool = False, values: Sequence[str] = (),
              plants: Sequence[Plant | str] = (),
              base_dir: Path | None = None,
              observe: Sequence[Callable[[Cell], None]] = ()) -> Iterator[Cell]:
    """Build and install the system of ``system_file``; shut it down (actuators safe) on exit.

    ``virtual``: virtual time against simulated slaves from the device maps; ``outputs=False``:
    actuator writes logged, not sent; ``workdir``: where sysfile.map goes (default a temporary
    directory). Without ``system.install`` every machine of the maps is loaded and nothing is
    installed. ``values`` (``DEVICE=SCRIPT``, as ``chcos sim --from --value``) and ``plants``
    (callables, or ``FILE.py:function`` references; see :data:`~chcos.apps.sim.from_map.Plant`)
    drive the simulated slaves, so they need ``virtual``; their files are relative to
    ``base_dir`` (default the current directory). ``observe`` are called with the cell once it
    is built, before its install script runs (the HIL evidence watches it from there:
    :mod:`chcos.hil.observe`). Raises ConfigError for a bad system file,
    device map, value script or plant (naming it), BusError if a bus cannot be opened,
    InstallError naming the script's file and line."""
    if (values or plants) and not virtual:
        raise ConfigError("value scripts and plant models drive the simulated slaves: they "
                          "need virtual time (--virtual)")
    sf = sysfile.load(system_file)
    devmap = load(list(sf.devmaps)) if sf.devmaps else None
    slaves = None
    tmp: tempfile.TemporaryDirectory[str] | None = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="chcos-run-")
        workdir = tmp.name
    work = Path(workdir)
    work.mkdir(parents=True, exist_ok=True)
    cell: Cell | None = None
    try:
        if devmap is not None and virtual:
            from chcos.apps.sim.from_map import load_plant, simulate

            slaves = simulate(devmap)
            devmap = slaves.devmap
            where = base_dir or Path.cwd()
            slaves.values(values, where)
            for plant in plants:
                slaves.add_plant(load_plant(plant, where) if isinstance(plant, str) else plant)
        elif values or plants:
            raise ConfigError(f"{sf.path}: value scripts and plant models need device maps "
                              "with simulated slaves; the system names none")
        holder: list[Cell] = []

        def logged(device: str, value: Any) -> None:
            if holder:
                holder[0].outputs_log.append((holder[0].now(), device, value))

        system = CellSystem(devmap if devmap is not None else (), outputs=outputs,
                            on_output=logged,
                            clock=clock or (VirtualClock() if virtual else SinceStartClock()),
                            task_path=list(sf.task_path), base_dir=sf.base_dir,
                            map_path=work / "sysfile.map")
        if slaves is not None:
            slaves.attach(system.kernel)
            system.devtab.peers_on_clock = True     # before the install starts the drivers
        counters = Counters()
        system.kernel.add_instrument(counters)
        cell = Cell(sf, system, counters, slaves, virtual)
        holder.append(cell)
        cell.start = system.kernel.clock.now()
        for watch in observe:
            watch(cell)
        if sf.install:
            for script in sf.install:
                cell.answers += system.run_script(script)
        else:
            machines = {d.machine for d in system.devmap.devices}
            for line in _boot_lines(sf, machines):
                cell.answers.append(system.execute(line))
    except BaseException:
        if cell is not None:
            cell.close()
        elif slaves is not None:
            slaves.close()
        if tmp is not None:
            tmp.cleanup()
        raise
    try:
        yield cell
    finally:
        try:
            cell.close()
        finally:
            if tmp is not None:
                tmp.cleanup()
