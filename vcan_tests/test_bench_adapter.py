"""The NBS executor run on a chcos System by chcos.apps.nbs.adapter: the kernel clock drives its
cycle (exact counts on virtual time) and the Devtab is its device I/O."""

from __future__ import annotations

import math

import pytest

from chcos.apps.nbs.adapter import DevtabIO, KernelScheduler, attach
from chcos.apps.nbs.executor import Level, LevelContext
from chcos.errors import DeviceError, KernelError
from vcan_tests.conftest import MakeSystem, memory_map


def _levels(n: int, log: list[str]) -> list[Level]:
    def mod(tag: str) -> object:
        def run(ctx: LevelContext) -> None:
            log.append(f"{tag}{ctx.level}")
        return run

    return [Level(g=mod("G"), m=mod("M"), h=mod("H")) for _ in range(n)]  # type: ignore[arg-type]


@pytest.mark.parametrize(("period", "seconds"), [(0.028, 1.0), (0.028, 10.0), (1 / 80, 2.0),
                                                 (0.0125, 3.0)])
def test_cycle_counts_are_exact_on_virtual_time(make_system: MakeSystem, period: float,
                                                seconds: float) -> None:
    s = make_system(memory_map(["S"], ["A"]))
    log: list[str] = []
    nbs = attach(s.kernel, s.devtab, _levels(3, log), period=period)
    nbs.start()
    fired = nbs.scheduler.run_until(seconds)
    cycles = math.floor(seconds / period + 1e-9)
    assert fired == nbs.executor.cycles == cycles
    assert nbs.executor.executions == 9 * cycles == len(log)
    assert log[:9] == ["G1", "M1", "H1", "G2", "M2", "H2", "G3", "M3", "H3"]
    assert s.kernel.clock.now() == pytest.approx(seconds)
    nbs.stop()
    assert nbs.scheduler.run_for(1.0) == 0


def test_devtab_io_reads_stamps_and_writes_through_devtab(make_system: MakeSystem) -> None:
    s = make_system(memory_map(["S"], ["A"]))
    io = DevtabIO(s.devtab)
    assert io.read("S") is None and io.arrived("S") is None
    s.run_for(0.5)
    s.devtab.inject("S", 4.0)
    s.run_for(0.25)
    assert io.read("S") == 4.0
    assert io.arrived("S") == pytest.approx(0.5)
    io.write("A", 12.0)
    assert s.devtab.get("A").value == 12.0
    assert s.devtab.get("A").driver.store.last("A") == 12.0  # type: ignore[union-attr]
    with pytest.raises(DeviceError, match="outside its limits"):
        io.write("A", 1000.0)
    with pytest.raises(DeviceError, match="actuator"):
        io.read("A")
    with pytest.raises(DeviceError, match="no device"):
        io.read("nope")


def test_nbs_reacts_on_its_next_cycle_to_a_devtab_value(make_system: MakeSystem) -> None:
    s = make_system(memory_map(["S"], ["A"]))

    def g(ctx: LevelContext) -> None:
        sample = ctx.poll("S")
        ctx.values["new"] = sample

    def h(ctx: LevelContext) -> None:
        sample = ctx.values.get("new")
        if sample is not None:
            ctx.write("A", 1.0)

    nbs = attach(s.kernel, s.devtab, [Level(g=g, m=lambda ctx: None, h=h)], period=0.028,
                 reactions={"A": ("S",)})
    nbs.start()
    s.kernel.call_at(0.100, lambda: s.devtab.inject("S", 3.0))
    nbs.scheduler.run_until(0.2)
    (lat,) = nbs.executor.latencies
    assert lat.visible == pytest.approx(0.100)
    assert lat.written == pytest.approx(0.112)   # the 4th cycle, at 4 x 28 ms
    assert s.devtab.get("A").value == 1.0


def test_a_failing_module_stops_the_run_with_kernel_error(make_system: MakeSystem) -> None:
    s = make_system(memory_map(["S"], ["A"]))

    def bad(ctx: LevelContext) -> None:
        if ctx.now > 0.1:
            raise ValueError("broken table")

    nbs = attach(s.kernel, s.devtab, [Level(g=bad, m=bad, h=bad)], period=0.028)
    nbs.start()
    with pytest.raises(KernelError, match="broken table"):
        nbs.scheduler.run_until(1.0)
    assert nbs.executor.cycles == 4
    with pytest.raises(KernelError, match="period"):
        KernelScheduler(s.kernel).every(0.0, lambda: None)
