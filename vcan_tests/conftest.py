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


def pytest_collection_finish(session: pytest.Session) -> None:
    """Start the long User-Mode-Linux runs of the selected tests marked ``uml_background`` (their
    module's ``start_in_background(config)``) now, so they overlap the rest of the session on
    the other core; each test then waits for its run's result."""
    for item in session.items:
        if isinstance(item, pytest.Function) and item.get_closest_marker("uml_background"):
            start = getattr(item.module, "start_in_background", None)
            if start is not None:
                start(item.config)


def pytest_sessionfinish(session: pytest.Session) -> None:
    """Stop background UML runs nobody collected (the session was interrupted)."""
    from vcan_tests.uml import BACKGROUND

    for run, _workdir in session.config.stash.get(BACKGROUND, {}).values():
        run.kill()
