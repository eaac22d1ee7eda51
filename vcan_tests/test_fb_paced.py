"""Polls paced by the polls (drivers.jobs): on the period's grid while the bus keeps up; while a
poll is in flight at most one successor waits and the host's timers stay quiet; a successor
already due when its predecessor is taken goes at once, counted ``polls-late``; nothing is armed
once the driver stops; and Devtab.at, the host side, runs a callback on the kernel thread at its
time when called from another thread."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

from chcos.devices.spec import BusSpec, DeviceMap
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System
from drivers.jobs import Job, JobOp, WorkerJobDriver
from vcan_tests.support_fb import WAIT, FakeHost, make_device


class StallDriver(WorkerJobDriver):
    """A job driver whose poll notes the host's time and then waits while ``gate`` is shut."""

    kind = "stall"

    def __init__(self, host: FakeHost, period: float) -> None:
        bus = BusSpec(name="b", kind="stall", key="bus[1]", options={})
        super().__init__(bus, [make_device("s", "sensor", "b")], host)
        self.period = period
        self.gate = threading.Event()
        self.gate.set()
        self.in_poll = threading.Event()
        self.taken: list[float] = []

    def start(self) -> None:
        self._start_worker()
        self._running = True
        self._poll_every("p", self.period)

    def stop(self) -> None:
        self._running = False
        self.gate.set()
        self._stop_worker()

    def _run(self, job: Job) -> None:
        if job.op == JobOp.POLL:
            self._poll_taken(job.what)
            self.taken.append(self.host.now())
            self.in_poll.set()
            self.gate.wait(WAIT)


def _rig() -> tuple[FakeHost, StallDriver]:
    host = FakeHost()
    driver = StallDriver(host, 0.1)
    driver.start()
    return host, driver


def test_polls_fall_on_the_grid_while_the_bus_keeps_up() -> None:
    host, driver = _rig()
    try:
        for _ in range(5):
            assert host.tick(0.1) == 1
            assert driver.settle(WAIT)
        assert [round(t, 9) for t in driver.taken] == [0.1, 0.2, 0.3, 0.4, 0.5]
        assert "polls-late" not in host.stats
        assert [round(p.due, 9) for p in host.periodics] == [0.6]
    finally:
        driver.stop()


def test_a_poll_in_flight_keeps_the_timers_quiet_and_its_late_successor_goes_at_once() -> None:
    host, driver = _rig()
    try:
        driver.gate.clear()
        assert host.tick(0.1) == 1                     # the poll due at 0.1 is taken, stalls
        assert driver.in_poll.wait(WAIT)
        assert host.tick(0.1) == 1                     # its successor, due 0.2, queued behind
        assert [host.tick(0.1) for _ in range(3)] == [0, 0, 0]   # nothing armed meanwhile
        assert driver._jobs.qsize() == 1               # one poll waiting, not one per period
        driver.gate.set()
        assert driver.settle(WAIT)
        # the successor, taken at 0.5, found its own successor (due 0.3) already due: queued at
        # once by the I/O thread, no kernel round trip; the next is a period after that
        assert [round(t, 9) for t in driver.taken] == [0.1, 0.5, 0.5]
        assert host.stats["polls-late"] == 1
        assert [round(p.due, 9) for p in host.periodics] == [0.6]
    finally:
        driver.stop()


def test_nothing_is_armed_once_the_driver_stops() -> None:
    host, driver = _rig()
    driver.gate.clear()
    assert host.tick(0.1) == 1
    assert driver.in_poll.wait(WAIT)
    assert host.tick(0.1) == 1                         # a successor waits in the queue
    driver.stop()                                      # drains it: taken, but not re-armed
    assert host.periodics == []
    assert host.tick(1.0) == 0


def test_devtab_at_from_another_thread_runs_on_the_kernel_thread_at_its_time() -> None:
    s = System(DeviceMap(), clock=VirtualClock(), machines=[0], base_dir=Path("."))
    seen: list[tuple[float, bool]] = []

    def note(what: Any = None) -> None:
        seen.append((s.kernel.clock.now(), s.kernel.on_kernel_thread()))

    t = threading.Thread(target=s.devtab.at, args=(5.0, note))
    t.start()
    t.join(WAIT)
    s.devtab.at(2.0, note)                             # not the kernel thread either
    s.run()
    assert seen == [(2.0, True), (5.0, True)]


class SlowBusDriver(StallDriver):
    """Every poll takes two periods of the host's clock (a bus slower than its poll period,
    so each successor is already due when its predecessor is taken: polled back to back); a
    write is recorded and confirmed."""

    def __init__(self, host: FakeHost, period: float) -> None:
        super().__init__(host, period)
        self.devices["a"] = make_device("a", "actuator", "b")
        self.sent: list[Any] = []

    def _run(self, job: Job) -> None:
        if job.op == JobOp.WRITE:
            self.sent.append(job.value)
            self.host.written(job.what, job.value)
            return
        with self.host.cond:
            self.host.clock += 2 * self.period
        super()._run(job)


def test_a_flush_is_not_held_up_by_polls_back_to_back() -> None:
    host = FakeHost()
    driver = SlowBusDriver(host, 0.1)
    driver.start()
    try:
        assert host.tick(0.1) == 1               # the first poll: from here on back to back
        assert host.wait_for(lambda h: h.stats.get("polls-late", 0) >= 3)
        driver.write("a", 7)                     # queued behind a poll
        assert driver.flush(WAIT)                # not held until its timeout by the polls
        assert host.writes == [("a", 7, "")] and driver.sent == [7]
        # meanwhile the late successor was armed through the host, not queued at once
        assert len(host.periodics) == 1 and host.periodics[0].due <= host.now()
        assert driver._jobs.qsize() == 0
        n = len(driver.taken)
        assert host.tick(0.0) == 1               # the host runs it: back to back again
        assert host.wait_for(lambda h: len(driver.taken) >= n + 3)
    finally:
        driver.stop()
