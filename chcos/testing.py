"""testing - the chcos pytest plugin: a user's own cell in their own CI.

Registered through the ``pytest11`` entry point, so any project with chcos installed gets the
``chcos_cell`` fixture. ``chcos_cell("system.toml")`` builds the system that file describes on
virtual time against simulated slaves generated from its device maps
(:mod:`chcos.apps.sim.from_map`), runs its install script, and returns a :class:`TestCell` to drive
and read it; every cell is shut down (actuators at their safe values) when the test ends::

    def test_valve_opens(chcos_cell):
        cell = chcos_cell("system.toml")       # relative to the pytest root directory
        cell.set("level", 100.0)               # the simulated PLC now serves 100 cm (held:
                                               # a value script waits for cell.release)
        cell.run_for(1.0)                      # one second of virtual time
        assert cell.value("level") == 100.0    # what Devtab holds
        assert cell.peer("valve") == 40        # what the simulated PLC was sent
        cell.silence("plc")                    # fault: the PLC stops answering
        cell.bus_fault("can0", "bus-off", 2.0) # fault: a CAN bus off for 2 s, then restarted
        cell.set("volts", raw=1400)            # a raw value past the DBC's limits
        cell.script("level", "ramp(0, 100, 10)")   # a value script, as chcos run --value
        cell.plant(tank)                       # tank(seconds, slaves) every 10 ms
        cell.invoke("fill", setpoint=80)       # a host command
        cell.assert_golden("tests/golden/fill.trace")   # the run so far against its golden trace

With ``pytest --chcos-coverage`` the plugin records which device states the tests' cells reached
(docs/hil-evidence.md; :mod:`chcos.hil.plugin` holds the options, the summary and the golden
traces: ``--chcos-update-golden`` writes them).

Results do not depend on the machine: the same maps, tasks and test give the same values at the
same virtual times on a laptop and on a loaded CI machine, whatever ``PYTHONHASHSEED`` (the
simulated slaves step on the virtual clock, virtual time waits for what drivers and slaves have
in flight, and no timeout on that path is taken from the wall clock: the kernel's contract for
drivers, :mod:`chcos.kernel.scheduler`; the exceptions still left, such as SYNC on wall time,
are listed in docs/first-cell.md, "Virtual time is deterministic", and measured by
``python -m tools.wallclock_audit``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator, Mapping
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

# the HIL evidence: options, summary, golden traces (chcos.hil.plugin imports chcos only when used)
from chcos.hil.plugin import (  # noqa: F401 (pytest finds the hooks and the fixture here)
    CellWatch,
    Evidence,
    chcos_golden,
    pytest_addoption,
    pytest_configure,
    pytest_sessionfinish,
    pytest_terminal_summary,
    pytest_testnodedown,
)

if TYPE_CHECKING:  # the plugin loads in every pytest run: import chcos only when used
    from chcos.apps.sim.from_map import Plant
    from chcos.cli.cellrun import Cell
    from chcos.hil.trace import Trace
    from chcos.tables.tasks import TaskEntry


class TestCell:
    """A user's system on virtual time, for tests (see the module doc)."""

    __test__ = False  # not a test class for pytest's collector

    def __init__(self, cell: Cell, watch: CellWatch | None = None) -> None:
        self.cell = cell
        self.system = cell.system
        self._watch = watch

    # ---- time -------------------------------------------------------------------------------
    def run_for(self, seconds: float) -> None:
        """Run ``seconds`` of virtual time (as fast as possible)."""
        self.cell.run_for(seconds)

    def run_until(self, condition: Callable[[], bool], *, step: float = 0.1,
                  limit: float = 60.0, timeout: float = 30.0) -> float:
        """Run virtual time in ``step``s until ``condition()`` holds; returns the virtual
        seconds it took. Raises TimeoutError, saying how long it ran, if ``condition`` still
        fails after ``limit`` virtual seconds. A cell whose drivers all run on the kernel
        thread (:attr:`chcos.devices.driver.Driver.settles` false) decides this on virtual time
        alone: the answer is the same on any machine. While a driver still works on threads of
        its own (a bus whose driver has not moved onto the kernel thread yet, issue 47), it may
        still decide something on the wall clock (a reconnect after a back-off), so past
        ``limit`` this waits up to ``timeout`` real seconds more, a ``step`` of real time at a
        time."""
        import time

        kernel = self.system.kernel
        start = self.now
        deadline: float | None = None
        while not condition():
            if self.now - start >= limit:
                if not kernel.settling:
                    raise TimeoutError(f"condition not met after {self.now - start:.1f} s of "
                                       f"virtual time")
                deadline = time.monotonic() + timeout if deadline is None else deadline
                if time.monotonic() >= deadline:
                    raise TimeoutError(f"condition not met after {self.now - start:.1f} s of "
                                       f"virtual time and {timeout:.0f} s of real time")
                time.sleep(step)    # let the drivers' own threads work
            self.cell.run_for(step)
        return self.now - start

    @property
    def now(self) -> float:
        """Seconds of virtual time since the cell was built."""
        return self.cell.now()

    # ---- host commands ----------------------------------------------------------------------
    def execute(self, line: str) -> str:
        """Any host command (``setpri -9 A B``, ``suspend T``...); raises ChcosError as the
        console would print it."""
        return self.system.execute(line)

    def invoke(self, task: str, priority: int | None = None, **command: Any) -> str:
        """Send ``task`` a command message from the host (``invoke task key=value...``)."""
        return self.system.invoke(task, command, priority)

    def inject(self, device: str, value: Any) -> None:
        """Feed a reading to ``device`` directly (bypassing its bus), as host ``inject`` does."""
        self.system.devtab.get(device)
        self.system.devtab.inject(device, value)

    # ---- the simulated slaves ---------------------------------------------------------------
    def set(self, device: str, value: Any = None, *, raw: Any = None) -> None:
        """Put ``value`` (engineering units) into the simulated slave serving sensor
        ``device`` - or ``raw``, the value on the wire before the device's scale and offset,
        anything the wire can carry (on CAN the signal's bits, past the DBC's minimum and
        maximum: a reading no real device should send) -; the system reads it at its next
        poll or frame. The value wins over the device's value script and plant until
        :meth:`release`. Raises DeviceError for a device with no simulated slave (use
        :meth:`inject`) or a raw value the wire cannot carry."""
        assert self.cell.slaves is not None
        self.cell.slaves.hold(device, value, raw=raw)

    def release(self, device: str) -> None:
        """End :meth:`set`'s hold of ``device``: its value script (or plant) drives it again.
        Raises DeviceError if it is not held."""
        assert self.cell.slaves is not None
        self.cell.slaves.release(device)

    def bus_fault(self, bus: str, kind: str, duration: float | None = None) -> None:
        """Fault on the simulated CAN bus ``bus``, as a test step: ``"error-frame"`` (one
        error frame; with ``duration`` one every 10 ms, the receive error counters climbing
        to error-passive), ``"error-passive"``, ``"bus-off"`` (every device of the bus fails
        with that reason; after the restart the actuators get their safe values first), or
        ``"recover"``; with ``duration`` seconds of virtual time the fault ends by itself
        (the controllers restart). Raises DeviceError for a bus that is no simulated CAN bus
        or an unknown fault."""
        assert self.cell.slaves is not None
        self.cell.slaves.bus_fault(bus, kind, duration)

    def bus_state(self, bus: str) -> dict[str, Any]:
        """What chcos reports of ``bus``'s controller (the driver's status ``bus_state``:
        ``state`` ("error-active", "error-warning", "error-passive", "bus-off"),
        ``tx_errors``, ``rx_errors``, ``bus_offs``, ``error_passive``, ``restarts``,
        ``error_frames``, ``last``); {} for a bus without one."""
        st = self.system.devtab.statuses().get(bus)
        if st is None or st.bus_state is None:
            return {}
        doc = dataclasses.asdict(st.bus_state)
        doc["state"] = st.bus_state.state.value
        return doc

    def peer(self, device: str) -> Any:
        """What the simulated slave holds for ``device``: for an actuator, what the system last
        put on the wire (engineering units)."""
        assert self.cell.slaves is not None
        return self.cell.slaves.get(device)

    def script(self, device: str, script: str | Callable[[float], float]) -> None:
        """Make sensor ``device`` follow a value script from now on (a function of the seconds
        since the start, or its text: ``ramp(0, 100, 10)``...)."""
        assert self.cell.slaves is not None
        self.cell.slaves.script(device, script)

    def plant(self, model: Plant) -> None:
        """Attach a plant model: ``model(seconds, slaves)`` every 10 ms of virtual time."""
        assert self.cell.slaves is not None
        self.cell.slaves.add_plant(model)

    def silence(self, bus: str) -> None:
        """Fault: the simulated slave of ``bus`` stops answering (its connection drops)."""
        assert self.cell.slaves is not None
        self.cell.slaves.silence(bus)

    def restore(self, bus: str) -> None:
        """The simulated slave of ``bus`` answers again, with the values it held."""
        assert self.cell.slaves is not None
        self.cell.slaves.restore(bus)

    def fail(self, device: str, reason: str = "failed by the test") -> None:
        """Fault: mark ``device`` failed, as its driver would: readers get SensorFailure, and
        a failed sensor delivers nothing (its readings are dropped, as every failed sensor's)
        until :meth:`recover`."""
        self.system.devtab.get(device)
        self.system.devtab.fail(device, reason)

    def recover(self, device: str, reason: str = "recovered in the test") -> None:
        """End the failure :meth:`fail` injected, as its driver's end event would (a reading
        alone never clears a failure the driver reported); a sensor is OK again with its next
        reading."""
        self.system.devtab.get(device)
        self.system.devtab.recover(device, reason)

    # ---- reading ----------------------------------------------------------------------------
    def value(self, device: str) -> Any:
        """Devtab's value of ``device`` (last reading, or last command of an actuator)."""
        return self.system.devtab.get(device).value

    def status(self, device: str) -> str:
        """Devtab's status of ``device``: ``OK``, ``failed``, ``stale`` or ``suspended``."""
        return self.system.devtab.get(device).status.value

    def task(self, name: str) -> TaskEntry:
        """The Tsktab entry of task ``name`` (``state``, ``steps``, ``abnormal``,
        ``last_error``...). Raises TaskError if there is none."""
        for t in self.system.tsktab:
            if t.name == name:
                return t
        from chcos.errors import TaskError

        raise TaskError(f"no task named {name!r}")

    def world(self, task: str) -> Any:
        """The world model of ``task`` (None if it has none)."""
        return self.task(task).world

    @property
    def outputs_log(self) -> list[tuple[float, str, Any]]:
        """Actuator writes logged instead of sent (``outputs=False``)."""
        return self.cell.outputs_log

    # ---- the run's trace (chcos.hil.trace) --------------------------------------------------
    def trace(self) -> Trace:
        """The cell's trace so far: every device value and status change, every command and its
        confirmation, bus errors and task events, on virtual time since the cell was built.
        Raises RuntimeError for a cell the ``chcos_cell`` fixture did not build."""
        if self._watch is None:
            raise RuntimeError("this cell is not watched: build it with the chcos_cell fixture")
        return self._watch.trace()

    def assert_golden(self, golden: str | Path, *, tolerance: Mapping[str, float] | None = None,
                      text: bool = False) -> None:
        """Assert that :meth:`trace` matches the golden trace file ``golden`` (relative to the
        pytest root directory), within ``tolerance`` per device (``{"level": 0.5}``); with
        ``pytest --chcos-update-golden`` write it instead. Raises AssertionError naming the
        first divergence of each device and task with its virtual time."""
        if self._watch is None:
            raise RuntimeError("this cell is not watched: build it with the chcos_cell fixture")
        self._watch.assert_golden(golden, tolerance=tolerance, text=text)

    def close(self) -> None:
        """Shut down now (actuators at their safe values); the fixture also does this."""
        self.cell.close()


@pytest.fixture
def chcos_cell(request: pytest.FixtureRequest,
               tmp_path: Path) -> Iterator[Callable[..., TestCell]]:
    """Factory ``chcos_cell(system_file, outputs=True, values=None, plant=None)`` ->
    :class:`TestCell`: the system on virtual time against simulated slaves; ``values`` maps
    sensors to value scripts (``{"level": "sine(50, 10, 4)"}``, as ``--value``), ``plant`` is a
    plant model (a callable ``(seconds, slaves)`` or ``FILE.py:function``). Relative paths
    start at the pytest root directory. Every cell is shut down at the end of the test."""
    from chcos.cli.cellrun import open_cell

    stack = ExitStack()
    built = [0]
    evidence = Evidence(request)
    stack.callback(evidence.finish)     # last: after every cell's shutdown
    root = Path(request.config.rootpath)

    def build(system_file: str | Path = "system.toml", *, outputs: bool = True,
              values: Mapping[str, str | float] | None = None,
              plant: Plant | str | None = None) -> TestCell:
        path = Path(system_file)
        if not path.is_absolute():
            path = root / path
        built[0] += 1
        work = tmp_path / f"chcos-cell-{built[0]}"
        items = [f"{name}={script}" for name, script in (values or {}).items()]
        cell = stack.enter_context(open_cell(path, virtual=True, outputs=outputs,
                                             workdir=work, values=items,
                                             plants=[plant] if plant is not None else [],
                                             base_dir=root, observe=[evidence.watch]))
        return TestCell(cell, evidence.watch_of(cell))

    with stack:
        yield build
