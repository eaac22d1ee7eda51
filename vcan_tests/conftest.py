"""Shared fixtures: a system on virtual time with in-memory devices."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from chcos.clock import VirtualClock
from chcos.devspec import BusSpec, DeviceMap, DeviceSpec
from chcos.system import System

MakeSystem = Callable[..., System]


def memory_map(sensors: dict[str, int] | list[str] = (), actuators: dict[str, float | None]
               | list[str] = (), **device_kw: object) -> DeviceMap:
    """A device map of in-memory sensors and actuators on machine 0 (actuators: name -> safe
    value)."""
    bus = BusSpec("mem", "memory")
    devs = []
    for name in sensors:
        devs.append(DeviceSpec(name, "sensor", 0, "mem", **device_kw))  # type: ignore[arg-type]
    acts = actuators if isinstance(actuators, dict) else dict.fromkeys(actuators, 0.0)
    for name, safe in acts.items():
        devs.append(DeviceSpec(name, "actuator", 0, "mem", safe_value=safe, limits=(-100, 100)))
    return DeviceMap((bus,), tuple(devs))


@pytest.fixture
def make_system(tmp_path: Path) -> Iterator[MakeSystem]:
    """Build Systems on a VirtualClock, booted on machine 0, shut down after the test."""
    made: list[System] = []

    def make(devmap: DeviceMap | None = None, machines: tuple[int, ...] = (0,),
             **kw: object) -> System:
        s = System(devmap if devmap is not None else DeviceMap(), clock=VirtualClock(),
                   machines=machines, base_dir=tmp_path, map_path=tmp_path / "sysfile.map",
                   **kw)  # type: ignore[arg-type]
        made.append(s)
        return s

    yield make
    for s in made:
        s.shutdown()
