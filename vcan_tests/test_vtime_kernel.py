"""The kernel's side of virtual time (issue 47, the contract in chcos.kernel.scheduler): a driver
on the kernel thread needs no settle and virtual time jumps when the system is idle; a driver on
threads of its own is settled before every jump, for as long as its SettleBound allows: a
simulated peer until it is done (SETTLE_TIMEOUT at most), a real peer at most the virtual time
to the next timer; the shutdown window makes no wall-clock decision."""

from __future__ import annotations

from typing import Any

import pytest

from chcos.devices.devtab import Devtab
from chcos.devices.driver import Driver
from chcos.devices.spec import BusSpec, DeviceMap, DeviceSpec
from chcos.kernel.clock import VirtualClock
from chcos.kernel.scheduler import SETTLE_TIMEOUT, Kernel, SettleBound
from tools.wallclock_audit import WallClockAudit


def test_without_settlers_virtual_time_jumps_and_no_wall_clock_is_read() -> None:
    k = Kernel(VirtualClock())
    fired: list[float] = []
    k.every(0.25, lambda: fired.append(k.clock.now()))
    with WallClockAudit() as audit:
        k.run(until=10.0)
        assert k.settle() is False       # nothing to settle: a peer's call costs nothing
    assert fired == pytest.approx([0.25 * i for i in range(1, 41)])
    assert not k.settling and audit.calls == {}


def test_each_settler_gets_the_timeout_of_its_bound() -> None:
    k = Kernel(VirtualClock())
    asked: dict[str, list[float]] = {"peer": [], "clock": []}
    k.add_settler(lambda t: asked["peer"].append(t) or True)
    k.add_settler(lambda t: asked["clock"].append(t) or True, SettleBound.CLOCK)
    k.call_at(0.004, lambda: None)     # the next timers: 4 ms, then 2 s later
    k.call_at(2.004, lambda: None)
    k.run(until=2.004)
    assert k.settling
    assert asked["peer"] and set(asked["peer"]) == {SETTLE_TIMEOUT}
    # a real peer may hold virtual time back at most as long as the virtual time to the next
    # timer: 4 ms before the first, 2 s before the second
    assert asked["clock"][0] == pytest.approx(0.004)
    assert any(t == pytest.approx(2.0) for t in asked["clock"])
    assert max(asked["clock"]) <= SETTLE_TIMEOUT


def test_a_settler_that_answers_late_is_waited_for_before_time_moves() -> None:
    """A simulated peer on a thread of its own: its answer (an interrupt) comes in the settle,
    and is handled at the instant it was asked for, before the next timer."""
    k = Kernel(VirtualClock())
    seen: list[tuple[str, float]] = []
    pending: list[str] = []

    def ask() -> None:
        pending.append("answer")

    def answer(what: str) -> None:
        seen.append((what, k.clock.now()))

    def settle(timeout: float) -> bool:
        while pending:
            k.interrupt(answer, pending.pop())
        return True

    k.add_settler(settle)
    k.call_at(1.0, ask)
    k.call_at(1.5, lambda: seen.append(("next timer", k.clock.now())))
    k.run(until=2.0)
    assert seen == [("answer", 1.0), ("next timer", 1.5)]


class _KernelThreadDriver(Driver):
    """A driver whose work all runs in kernel timers (as the protocol-free binding's)."""

    kind = "test-kernel-thread"
    settles = False

    def start(self) -> None:
        self._running = True
        self.host.every(0.01, lambda: None)

    def _write(self, device: str, value: Any) -> None:
        self.host.written(device, value)

    def stop(self) -> None:
        self._running = False

    def settle(self, timeout: float) -> bool:
        raise AssertionError("a driver on the kernel thread is never settled")


class _ThreadedDriver(_KernelThreadDriver):
    kind = "test-threaded"
    settles = True

    def settle(self, timeout: float) -> bool:
        return True


@pytest.mark.parametrize("cls", [_KernelThreadDriver, _ThreadedDriver])
def test_devtab_settles_only_drivers_with_work_on_threads(cls: type[Driver],
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    from chcos.devices import registry

    monkeypatch.setattr(registry, "driver_class", lambda kind: cls)
    k = Kernel(VirtualClock())
    dt = Devtab(k)
    bus = BusSpec(name="b", kind=cls.kind)
    dev = DeviceSpec(name="s", direction="sensor", machine=0, bus="b")
    devmap = DeviceMap(buses=(bus,), devices=(dev,))
    dt.load(devmap)
    dt.start_drivers(devmap)
    assert k.settling is cls.settles
    k.run(until=1.0)
    assert k.clock.now() == pytest.approx(1.0)
    dt.stop_drivers()


def test_the_virtual_shutdown_window_reads_no_wall_clock() -> None:
    k = Kernel(VirtualClock())
    fired: list[float] = []
    k.every(0.1, lambda: fired.append(k.clock.now()))
    with WallClockAudit() as audit:
        k.run_drivers(1.0, lambda: len(fired) >= 5)
        k.run_drivers(2.0, lambda: False)
    assert fired[:5] == pytest.approx([0.1, 0.2, 0.3, 0.4, 0.5])
    assert k.clock.now() == pytest.approx(2.0)
    assert audit.calls == {}

