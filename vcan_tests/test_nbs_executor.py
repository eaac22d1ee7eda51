"""NBS cyclic executor: virtual scheduler, exact cycle counts, latency, table-driven H modules."""

from __future__ import annotations

import math

import pytest

from chcos.apps.nbs.executor import (
    CommonMemory,
    DeviceIO,
    Level,
    LevelContext,
    Module,
    NbsExecutor,
    Order,
    TableH,
)
from chcos.apps.nbs.scheduling import VirtualScheduler
from chcos.apps.nbs.statetable import Call, load_builtin
from chcos.errors import KernelError


class Devices:
    """In-memory sensors (with arrival stamps) and actuators on a virtual scheduler."""

    def __init__(self, sched: VirtualScheduler) -> None:
        self.sched = sched
        self.values: dict[str, object] = {}
        self.stamps: dict[str, float] = {}
        self.log: list[tuple[float, str, object]] = []

    def set(self, name: str, value: object) -> None:
        self.values[name] = value
        self.stamps[name] = self.sched.now()

    def write(self, name: str, value: object) -> None:
        self.values[name] = value
        self.log.append((self.sched.now(), name, value))

    def io(self, stamped: bool = True) -> DeviceIO:
        return DeviceIO(self.values.get, self.write, self.stamps.get if stamped else None)


def idle(ctx: LevelContext) -> None:
    """A module that does nothing (it still counts as executed)."""


# ---------------------------------------------------------------- virtual scheduler


def test_virtual_scheduler_fires_in_time_order_fifo_on_ties() -> None:
    s = VirtualScheduler()
    fired: list[tuple[float, str]] = []
    s.every(0.5, lambda: fired.append((s.now(), "a")))
    s.call_at(1.0, lambda: fired.append((s.now(), "b")))
    s.every(0.25, lambda: fired.append((s.now(), "c")))
    assert s.run_until(1.0) == 7
    assert fired == [
        (0.25, "c"), (0.5, "a"), (0.5, "c"), (0.75, "c"), (1.0, "a"), (1.0, "b"), (1.0, "c"),
    ]
    assert s.now() == 1.0


def test_virtual_scheduler_has_no_drift_and_cancels() -> None:
    s = VirtualScheduler()
    times: list[float] = []
    t = s.every(0.028, lambda: times.append(s.now()))
    s.run_until(100.0)
    assert len(times) == 3571
    assert times[-1] == 3571 * 0.028  # origin + k*period, not a running sum
    t.cancel()
    t.cancel()
    assert s.run_for(1.0) == 0 and s.now() == 101.0


def test_virtual_scheduler_rejects_bad_requests() -> None:
    s = VirtualScheduler(start=5.0)
    with pytest.raises(KernelError, match="period must be > 0"):
        s.every(0, lambda: None)
    with pytest.raises(KernelError, match="before now"):
        s.call_at(4.0, lambda: None)


# ---------------------------------------------------------------- cycles and counts


def three_levels(trace: list[str] | None = None) -> list[Level]:
    def mod(name: str) -> Module:
        def run(ctx: LevelContext) -> None:
            if trace is not None:
                trace.append(f"{name}{ctx.level}")

        return run

    return [Level(g=mod("G"), m=mod("M"), h=mod("H")) for _ in range(3)]


@pytest.mark.parametrize(("period", "seconds", "cycles"), [
    (0.028, 10.0, 357),      # 10 / 0.028 = 357.1
    (1 / 80, 10.0, 800),     # the thesis' 80 Hz polling rate
    (0.028, 0.027, 0),       # shorter than one period: nothing runs
])
def test_every_fsm_runs_every_cycle_exactly(period: float, seconds: float, cycles: int) -> None:
    sched = VirtualScheduler()
    ex = NbsExecutor(three_levels(), Devices(sched).io(), sched, period=period)
    ex.start()
    sched.run_until(seconds)
    assert cycles == math.floor(seconds / period + 1e-9)
    assert ex.cycles == cycles
    assert ex.counts == {f"{k}{n}": cycles for n in (1, 2, 3) for k in "GMH"}
    assert ex.executions == 9 * cycles


def test_cycle_runs_levels_bottom_up_g_m_h() -> None:
    trace: list[str] = []
    sched = VirtualScheduler()
    ex = NbsExecutor(three_levels(trace), Devices(sched).io(), sched)
    ex.cycle()
    assert trace == ["G1", "M1", "H1", "G2", "M2", "H2", "G3", "M3", "H3"]


def test_start_stop_and_misuse() -> None:
    sched = VirtualScheduler()
    ex = NbsExecutor(three_levels(), Devices(sched).io(), sched, period=0.1)
    ex.start()
    with pytest.raises(KernelError, match="already started"):
        ex.start()
    sched.run_until(1.0)
    ex.stop()
    sched.run_until(2.0)
    assert ex.cycles == 10
    ex.start()
    sched.run_until(2.5)
    assert ex.cycles == 15
    with pytest.raises(KernelError, match="at least one level"):
        NbsExecutor([], Devices(sched).io(), sched)
    with pytest.raises(KernelError, match="period must be > 0"):
        NbsExecutor(three_levels(), Devices(sched).io(), sched, period=-1)
    with pytest.raises(KernelError, match="no level 4"):
        ex.report(4)
    with pytest.raises(KernelError, match="no level 0"):
        ex.context(0)


# ---------------------------------------------------------------- polling and latency


def reflex_level() -> Level:
    """G polls "s"; H copies every new value to actuator "a"."""

    def g(ctx: LevelContext) -> None:
        ctx.values["new"] = ctx.poll("s")

    def h(ctx: LevelContext) -> None:
        sample = ctx.values.get("new")
        if sample is not None:
            ctx.write("a", sample.value)  # type: ignore[attr-defined]

    return Level(g=g, m=idle, h=h)


def test_latency_is_quantised_to_the_cycle() -> None:
    sched = VirtualScheduler()
    dev = Devices(sched)
    ex = NbsExecutor([reflex_level()], dev.io(), sched, reactions={"a": ["s"]})
    changes = [0.010, 0.056, 0.100, 0.1234, 0.5]  # 0.056 falls exactly on cycle 2
    for i, t in enumerate(changes):
        sched.call_at(t, lambda i=i: dev.set("s", i))  # type: ignore[misc]
    ex.start()
    sched.run_until(1.0)
    assert [x.sensor for x in ex.latencies] == ["s"] * len(changes)
    for lat, t in zip(ex.latencies, changes, strict=True):
        assert lat.visible == t
        k = math.ceil(t / 0.028 - 1e-9)
        assert lat.written == pytest.approx(k * 0.028)
        assert 0 <= lat.seconds < 0.028 + 1e-12
    assert [v for _, _, v in dev.log] == [0, 1, 2, 3, 4]


def test_oldest_unanswered_value_sets_the_latency() -> None:
    sched = VirtualScheduler()
    dev = Devices(sched)
    ex = NbsExecutor([reflex_level()], dev.io(), sched, reactions={"a": ["s"]})
    sched.call_at(0.001, lambda: dev.set("s", 1))
    sched.call_at(0.020, lambda: dev.set("s", 2))  # overwrites 1 before the poll at 0.028
    ex.start()
    sched.run_until(0.1)
    [lat] = ex.latencies
    assert lat.visible == 0.020  # value 1 was never seen: it cannot be reacted to
    assert dev.log == [(0.028, "a", 2)]


def test_without_arrival_stamps_changes_are_detected_by_value() -> None:
    sched = VirtualScheduler()
    dev = Devices(sched)
    ex = NbsExecutor([reflex_level()], dev.io(stamped=False), sched, reactions={"a": ["s"]})
    sched.call_at(0.01, lambda: dev.set("s", 7))
    sched.call_at(0.04, lambda: dev.set("s", 7))  # same value again: not a new sample
    sched.call_at(0.07, lambda: dev.set("s", 8))
    ex.start()
    sched.run_until(0.2)
    assert [v for _, _, v in dev.log] == [7, 8]
    assert [lat.seconds for lat in ex.latencies] == [0.0, 0.0]  # visible when polled


def test_poll_of_a_sensor_without_value_is_none() -> None:
    sched = VirtualScheduler()
    ex = NbsExecutor([reflex_level()], Devices(sched).io(), sched)
    ex.cycle()
    assert ex.context(1).poll("s") is None and ex.context(1).read("s") is None
    assert ex.writes == 0 and ex.latencies == []


# ---------------------------------------------------------------- table-driven H modules


class WeldPlant:
    """Gas valve -> gas flow; arc voltage -> arc temperature (100 degrees per volt)."""

    THRESHOLD = 800.0

    def __init__(self, sched: VirtualScheduler, bottle_full: bool = True) -> None:
        self.dev = Devices(sched)
        self.dev.set("gas_valve", 0)
        self.dev.set("arc_voltage", 0)
        self.bottle_full = bottle_full
        self.h1_calls: list[str] = []

    def flowing(self) -> bool:
        return bool(self.dev.values["gas_valve"]) and self.bottle_full

    def temp(self) -> float:
        return float(self.dev.values["arc_voltage"]) * 100.0  # type: ignore[arg-type]

    def actuate(self, call: Call, ctx: LevelContext) -> None:
        self.h1_calls.append(call.name)
        volts = ctx.read("arc_voltage")
        assert isinstance(volts, int)
        if call.name == "OPEN VALVE":
            ctx.write("gas_valve", 1)
        elif call.name == "CLOSE VALVE":
            ctx.write("gas_valve", 0)
        elif call.name == "INCR VOLTAGE":
            ctx.write("arc_voltage", volts + 1)
        elif call.name == "CUT VOLTAGE":
            ctx.write("arc_voltage", 0)

    def g1(self, ctx: LevelContext) -> None:
        flowing, hot = self.flowing(), self.temp() >= self.THRESHOLD
        ctx.facts.update({
            "gas flowing": flowing, "gas not flowing": not flowing,
            "bottle full": self.bottle_full, "bottle empty": not self.bottle_full,
            "arc on": hot, "arc off": not hot, "timeout": False,
        })
        ctx.values.update({"temp": self.temp(), "threshold": self.THRESHOLD})

    def g2(self, ctx: LevelContext) -> None:
        flowing, hot = self.flowing(), self.temp() >= self.THRESHOLD
        ctx.facts.update({"gas on": flowing, "gas off": not flowing,
                          "arc on": hot, "arc off": not hot, "timeout": False})

    def levels(self) -> list[Level]:
        return [
            Level(g=self.g1, m=idle, h=TableH(load_builtin("H1"), actuate=self.actuate)),
            Level(g=self.g2, m=idle, h=TableH(load_builtin("H2"))),
        ]


def test_h2_turn_on_weld_drives_h1_through_common_memory() -> None:
    sched = VirtualScheduler()
    plant = WeldPlant(sched)
    ex = NbsExecutor(plant.levels(), plant.dev.io(), sched)
    ex.command("TURN ON WELD")
    ex.start()
    sched.run_until(1.0)
    assert ex.report() == "weld on"
    assert plant.dev.values["gas_valve"] == 1 and plant.dev.values["arc_voltage"] == 8
    # cycle 1: H2 issues TURN ON INERT GAS; 2: H1 opens the valve; 3: H1 "gas on", H2 issues
    # TURN ON ARC; 4..11: H1 raises the voltage 8 times; 12: H1 "arc on"; 12: H2 "weld on".
    assert plant.h1_calls == ["OPEN VALVE"] + ["INCR VOLTAGE"] * 8 + ["KEEP VOLTAGE"]
    assert [t for t, name, _ in plant.dev.log if name == "gas_valve"] == [pytest.approx(0.056)]
    h1_order = ex.memory.get(CommonMemory.cmd(1))
    assert isinstance(h1_order, Order) and h1_order.call == Call("TURN ON ARC")
    assert ex.report(1) == "arc on"


def test_h2_sees_no_stale_report_from_an_earlier_command() -> None:
    sched = VirtualScheduler()
    plant = WeldPlant(sched)
    ex = NbsExecutor(plant.levels(), plant.dev.io(), sched)
    ex.command("TURN ON WELD")
    ex.start()
    sched.run_until(1.0)
    assert ex.report(1) == "arc on"
    # GOTO HOME: H1's standing "arc on" answers another command, so H2 must not read it;
    # it issues MOVE TO P(home) on its first step.
    ex.context(2).values["home"] = "HOME"
    ex.command("GOTO HOME")
    ex.cycle()
    order = ex.memory.get(CommonMemory.cmd(1))
    assert isinstance(order, Order) and order.call == Call("MOVE TO P", ("HOME",))
    assert ex.report() == "notat home"


def test_bottle_empty_closes_the_valve_and_reports_it() -> None:
    sched = VirtualScheduler()
    plant = WeldPlant(sched, bottle_full=False)
    ex = NbsExecutor(plant.levels(), plant.dev.io(), sched)
    ex.command("TURN ON WELD")
    ex.start()
    sched.run_until(0.5)
    assert ex.report(1) == "bottle empty"
    assert plant.h1_calls[0] == "CLOSE VALVE"
    assert plant.dev.values["gas_valve"] == 0
    assert ex.report() == "weld off"


def test_h3_stop_runs_down_three_table_levels() -> None:
    sched = VirtualScheduler()
    plant = WeldPlant(sched)
    plant.dev.set("motors", 1)
    plant.dev.set("gas_valve", 1)
    plant.dev.set("arc_voltage", 9)
    base_g1 = plant.g1

    def g1(ctx: LevelContext) -> None:
        base_g1(ctx)
        on = bool(plant.dev.values["motors"])
        ctx.facts.update({"motors on": on, "motors off": not on})

    calls: list[Call] = []

    def actuate(call: Call, ctx: LevelContext) -> None:
        calls.append(call)
        if call.name == "MOTORS OFF":
            ctx.write("motors", 0)
        plant.actuate(call, ctx)

    levels = [
        Level(g=g1, m=idle, h=TableH(load_builtin("H1"), actuate=actuate)),
        Level(g=plant.g2, m=idle, h=TableH(load_builtin("H2"))),
        Level(g=idle, m=idle, h=TableH(load_builtin("H3"))),
    ]
    ex = NbsExecutor(levels, plant.dev.io(), sched)
    ex.command("STOP", "P7")
    ex.start()
    sched.run_until(1.0)
    assert [ex.report(n) for n in (1, 2, 3)] == ["gas off", "stopped", "stopped"]
    assert plant.h1_calls == ["MOTORS OFF", "MEMORIZE", "CUT VOLTAGE", "CLOSE VALVE"]
    assert [(name, v) for _, name, v in plant.dev.log] == [
        ("motors", 0), ("arc_voltage", 0), ("gas_valve", 0)]
    assert Call("MEMORIZE", ("P7",)) in calls  # H3's pos reached H1 through H2's position
