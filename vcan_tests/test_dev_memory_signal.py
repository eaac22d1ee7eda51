"""The bus-less drivers: memory (host-fed sensors, kept writes) and signal (clocked waveforms)."""

from __future__ import annotations

import math
import random
import threading
from collections import deque
from pathlib import Path
from typing import Any

import pytest

from chcos.devices.devmap import load
from chcos.devices.options import parsed
from chcos.errors import DeviceError
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System
from chcos.tables.tasks import TaskEntry
from drivers.memory import HISTORY_BYTES, ActuatorStore, MemoryDriver, _size
from drivers.registry import driver_class
from drivers.signal import SignalDriver, WaveAddress, make_waveform
from vcan_tests.support_dev import FakeHost, bus, device

ROOT = Path(__file__).resolve().parent.parent


def test_registry_finds_the_bus_less_drivers() -> None:
    assert driver_class("memory") is MemoryDriver and driver_class("signal") is SignalDriver


def test_memory_keeps_bounded_history_and_feeds_sensors_from_the_host() -> None:
    host = FakeHost()
    drv = MemoryDriver(bus("memory", history=3),
                       [device("P", "sensor", i=0), device("V", "actuator", i=1)], host)
    drv.start()
    assert drv.store.last("V") is None
    for v in range(5):
        drv.write("V", v)
    assert drv.store.history("V") == [2, 3, 4] and drv.store.last("V") == 4
    assert drv.store.count("V") == 5 and drv.store.wait_for("V", lambda v: v == 4, 0.0)
    assert not drv.store.wait_for("V", lambda v: v == 9, 0.01)
    drv.inject("P", 1.25)
    assert host.delivered == [("P", 1.25)]
    with pytest.raises(DeviceError, match="expected one of its sensors P"):
        drv.inject("V", 1.0)
    with pytest.raises(DeviceError, match="not an actuator of this bus; expected one of V"):
        drv.write("P", 1.0)
    assert drv.settle(0.0)
    drv.stop()


def test_memory_check_rejects_options_and_addresses() -> None:
    assert MemoryDriver.check_bus(bus("memory", history=0)) == [
        "bus[0].history: expected an integer 1..1000000, got 0"]
    assert MemoryDriver.check_device(bus("memory"), device("A", "sensor", x=1)) == [
        "device[0].address.x: unknown key; a memory device takes no address"]


def _wave(address: dict[str, Any]) -> WaveAddress:
    return parsed(WaveAddress, {"rate_hz": 1, **address}, "address")


@pytest.mark.parametrize(("address", "samples"), [
    ({"waveform": "sine", "amplitude": 2.0, "period": 4.0}, [0.0, 2.0, 0.0, -2.0]),
    ({"waveform": "square", "center": 1.0, "period": 2.0}, [2.0, 0.0, 2.0, 0.0]),
    ({"waveform": "ramp", "amplitude": 1.0, "period": 4.0}, [-1.0, -0.5, 0.0, 0.5]),
    ({"waveform": "constant", "value": 7.5}, [7.5, 7.5, 7.5, 7.5]),
])
def test_waveforms(address: dict[str, float], samples: list[float]) -> None:
    wave = make_waveform(_wave(address))
    assert [wave(t) for t in (0.0, 1.0, 2.0, 3.0)] == [pytest.approx(s, abs=1e-9)
                                                       for s in samples]


def test_random_waveform_is_seeded_and_bounded() -> None:
    a = make_waveform(_wave({"waveform": "random", "seed": 3, "center": 10.0, "amplitude": 1.0}))
    b = make_waveform(_wave({"waveform": "random", "seed": 3, "center": 10.0, "amplitude": 1.0}))
    xs = [a(0.0) for _ in range(50)]
    assert xs == [b(0.0) for _ in range(50)] and all(9.0 <= x <= 11.0 for x in xs)
    assert len(set(xs)) == 50


def test_fig65_runs_on_virtual_time() -> None:
    dm = load(ROOT / "chcos" / "apps" / "fig65" / "fig65.toml")
    host = FakeHost()
    spec = dm.buses[0]
    drv = SignalDriver(spec, dm.devices_on(spec.name), host)
    drv.start()
    assert sorted(p for p, _, _ in host.timers) == [0.1, 0.1, 0.1]
    host.advance(1.0)
    for name in ("S1", "S2", "S3"):
        assert len(host.values(name)) == 10
    s1 = host.values("S1")
    assert s1[0] == pytest.approx(50.0 + 50.0 * math.sin(2 * math.pi * 0.1 / 4.0))
    assert all(0.0 <= v <= 100.0 for v in s1)
    assert set(host.values("S2")[:9]) == {2.0}        # the high half of a 2 s square
    drv.write("M1", 12.0)
    assert drv.store.last("M1") == 12.0
    drv.stop()
    host.advance(1.0)
    assert len(host.values("S1")) == 10 and drv.samples == 30


def test_signal_check_device() -> None:
    errs = SignalDriver.check_device(bus("signal"), device(
        "S", "sensor", waveform="sine", rate_hz=0, period=-1, colour=1))
    assert errs == [
        "device[0].address.colour: unknown key for the waveform variant; expected one of "
        "amplitude, center, period, phase, rate_hz, seed, value, waveform",
        "device[0].address.rate_hz: expected a finite value > 0, got 0",
        "device[0].address.period: expected a finite value > 0, got -1"]
    assert SignalDriver.check_device(bus("signal"), device(
        "S", "sensor", waveform="saw", rate_hz=5)) == [
        "device[0].address.waveform: expected one of 'sine', 'square', 'ramp', 'constant', "
        "'random', 'echo', got 'saw'"]


def test_memory_history_keeps_what_a_recount_would_keep() -> None:
    """The kept history (bounded by count and by HISTORY_BYTES, with a running byte total)
    against a model that recounts every kept value's size after each write: random sizes
    around the byte bound, a small count bound, numbers and strings mixed."""
    rng = random.Random(7)
    store = ActuatorStore(["M"], history=4)
    model: deque[object] = deque(maxlen=4)
    for i in range(2000):
        value: object = (i if rng.random() < 0.3
                         else "x" * rng.choice([1, 100, HISTORY_BYTES // 3, HISTORY_BYTES // 2,
                                                HISTORY_BYTES + 1]))
        model.append(value)
        while len(model) > 1 and sum(_size(v) for v in model) > HISTORY_BYTES:
            model.popleft()
        store.put("M", value)
        assert store.history("M") == list(model), i
    assert store.count("M") == 2000


def test_a_reading_on_the_kernel_thread_is_handled_at_once_and_elsewhere_as_an_interrupt(
        tmp_path: Path) -> None:
    """Devtab.deliver_now (the signal driver's samplers use it): in a timer callback on the
    kernel thread the reading is in the device's buffer before the call returns; in a task's
    step, or from another thread, it is an interrupt, handled after the step (or when the
    kernel next runs), as Devtab.deliver."""
    s = System(load(ROOT / "chcos" / "apps" / "fig65" / "fig65.toml"), clock=VirtualClock(),
               base_dir=tmp_path)
    s.start_drivers([1])  # (S3's machine): samples at 0.1, 0.2...
    dt, k = s.devtab, s.kernel
    seen: list[tuple[str, float, int]] = []

    def note(where: str) -> None:
        e = dt.get("S3")
        seen.append((where, e.value, e.readings))

    def in_timer() -> None:
        dt.deliver_now("S3", 15.0)     # within S3's limits (a reading outside fails it)
        note("timer")

    async def in_step() -> None:
        dt.deliver_now("S3", 16.0)
        note("step")

    k.call_at(0.05, in_timer)  # between two samples of the 10 Hz signals
    s.run(until=0.06)
    assert seen == [("timer", 15.0 * dt.get("S3").spec.scale + dt.get("S3").spec.offset, 1)]
    t = TaskEntry(tid=99, name="X", machine=0, level=1, func=lambda *a: None)  # type: ignore
    t.coro = in_step()
    k.ready(t, 50)
    s.run(until=0.07)
    assert seen[1] == ("step", seen[0][1], 1) and dt.get("S3").readings == 2  # after the step
    other = threading.Thread(target=dt.deliver_now, args=("S3", 17.0))
    other.start()
    other.join()
    assert dt.get("S3").readings == 2
    s.run(until=0.08)
    assert dt.get("S3").readings == 3
    s.run(until=1.0)
    assert dt.get("S3").readings == 3 + 10  # and the driver's own samples: 10 in a second
    assert dt.stop_drivers() == []


ECHO_MAP = """
[[bus]]
name = "plant"
kind = "signal"

[[device]]
name = "S"
direction = "sensor"
bus = "plant"
address = {{ waveform = "echo", actuator = "{actuator}", rate_hz = 10, value = 1.0 }}

[[device]]
name = "M"
direction = "actuator"
machine = {machine}
bus = "plant"
safe_value = 0.0

[[device]]
name = "T"
direction = "sensor"
bus = "plant"
address = {{ waveform = "constant", rate_hz = 10 }}
"""


def test_echo_sensor_reads_its_actuator_back_at_once_and_every_sample() -> None:
    host = FakeHost()
    drv = SignalDriver(bus("signal"), [
        device("S", "sensor", waveform="echo", actuator="M", rate_hz=10, value=1.5),
        device("M", "actuator", i=1), device("N", "actuator", i=2)], host)
    drv.start()
    host.advance(0.1)
    assert host.delivered == [("S", 1.5)]          # before any write: ``value``
    drv.write("M", 3.0)
    drv.write("N", 9.0)                            # not echoed
    assert host.delivered[1:] == [("S", 3.0)]      # at once, before any sample
    host.advance(0.2)
    assert host.delivered[2:] == [("S", 3.0), ("S", 3.0)]   # the samples hold it
    assert drv.store.last("M") == 3.0 and drv.store.last("N") == 9.0
    drv.stop()
    with pytest.raises(DeviceError, match="not running"):
        drv.write("M", 4.0)
    assert host.values("S") == [1.5, 3.0, 3.0, 3.0]   # a refused write echoes nothing
    with pytest.raises(ValueError, match="no waveform of time"):
        make_waveform(_wave({"waveform": "echo"}))


def test_echo_address_check() -> None:
    b = bus("signal")
    assert SignalDriver.check_device(b, device(
        "S", "sensor", waveform="echo", rate_hz=5, actuator="M", value=2.0)) == []
    assert SignalDriver.check_device(b, device(
        "S", "sensor", waveform="echo", rate_hz=5, amplitude=1.0)) == [
        "device[0].address.amplitude: unknown key for the echo variant; expected one of "
        "actuator, rate_hz, value, waveform",
        "device[0].address.actuator: required; expected a string"]
    assert SignalDriver.check_device(b, device(
        "S", "sensor", waveform="sine", rate_hz=5, actuator="M")) == [
        "device[0].address.actuator: unknown key for the waveform variant; expected one of "
        "amplitude, center, period, phase, rate_hz, seed, value, waveform"]
    assert SignalDriver.check_device(b, device("A", "actuator", x=1)) == [
        "device[0].address.x: unknown key; an actuator on a signal bus takes no address"]


@pytest.mark.parametrize(("actuator", "machine", "error"), [
    ("M9", 0, "device[0].address.actuator: expected an actuator of bus 'plant' on machine 0 "
              "(M), got 'M9'"),
    ("T", 0, "device[0].address.actuator: expected an actuator of bus 'plant' on machine 0 "
             "(M), got 'T'"),                      # a sensor
    ("M", 1, "device[0].address.actuator: expected an actuator of bus 'plant' on machine 0 "
             "(it has none), got 'M'"),            # another machine's
])
def test_an_echo_of_no_actuator_of_its_own_rejects_the_map(
        tmp_path: Path, actuator: str, machine: int, error: str) -> None:
    from chcos.devices.devmap import check

    path = tmp_path / "plant.toml"
    path.write_text(ECHO_MAP.format(actuator=actuator, machine=machine))
    dmap, errors, _ = check(path)
    assert dmap is None and len(errors) == 1
    assert str(path) in errors[0] and error in errors[0]


async def echo_loop(ctx: Any, cmd: dict[str, Any]) -> None:
    """Reads its sensor, answers each reading with the reading + 1, ``cmd["n"]`` times."""
    log = cmd["log"]
    for _ in range(int(cmd["n"])):
        v = await ctx.read(0)
        log.append((ctx.now, v))
        ctx.write(0, v + 1.0)
    await ctx.sleep(1e9)


def test_echo_runs_a_loop_flat_out_every_reading_served(tmp_path: Path) -> None:
    """A task that answers each reading of an echo sensor with a write: the first sample
    starts it and every write is read back at once (no time passes on the virtual clock),
    through the interrupt queue, none overwritten unread; the samples after hold the last
    write."""
    path = tmp_path / "plant.toml"
    path.write_text(ECHO_MAP.format(actuator="M", machine=0))
    s = System(load(path), clock=VirtualClock(), base_dir=tmp_path)
    s.execute("install -m0 sysfile")
    s.execute("install -m0i1o1 --code=vcan_tests.test_dev_memory_signal:echo_loop A S M")
    log: list[tuple[float, float]] = []
    s.invoke("A", {"log": log, "n": 50}, priority=20)
    s.run(until=0.15)
    assert log == [(pytest.approx(0.1), float(v)) for v in range(1, 51)]
    e = s.devtab.get("S")
    assert e.readings == 51 and e.overwrites == 0 and e.value == 51.0  # the last, unread
    s.run(until=0.25)
    assert s.devtab.get("S").readings == 52 and s.devtab.get("S").value == 51.0
    assert s.devtab.stop_drivers() == []


def test_a_check_between_devices_that_raises_is_an_error_naming_the_bus(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from chcos.devices.devmap import check

    def broken(cls: type, bus: Any, devices: Any) -> list[Any]:
        raise KeyError("x")

    monkeypatch.setattr(SignalDriver, "check_devices", classmethod(broken))
    path = tmp_path / "plant.toml"
    path.write_text(ECHO_MAP.format(actuator="M", machine=0))
    dmap, errors, _ = check(path)
    assert dmap is None and len(errors) == 1
    assert f"{path}" in errors[0] and "bus[0]" in errors[0] and "could not be checked" in errors[0]
