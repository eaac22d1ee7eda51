"""Devtab as the composition of its parts (the table, health, command checks, write tracking,
bus counters), seen through its public interface: a clashing load enters nothing, an unknown
device is named, the link to other satellites set after construction reaches both the
commands and the status reports, and a status change is heard by the listeners."""

from __future__ import annotations

from typing import Any

import pytest

from chcos.devices.devtab import Devtab
from chcos.devices.entry import DeviceStatus
from chcos.errors import DeviceError, SensorFailure
from chcos.kernel.clock import VirtualClock
from chcos.kernel.scheduler import Kernel
from vcan_tests.conftest import memory_map


class Remote:
    """The devices of other satellites, as a link would carry them: what it was handed."""

    def __init__(self) -> None:
        self.commands: list[tuple[str, int, Any, str]] = []
        self.statuses: list[tuple[str, DeviceStatus, str]] = []

    def actuator(self, device: str, machine: int, value: Any, source: str) -> None:
        self.commands.append((device, machine, value, source))

    def device_status(self, device: str, status: DeviceStatus, reason: str) -> None:
        self.statuses.append((device, status, reason))


class Listener:
    """The message manager's side: readings and sensor failures."""

    def __init__(self) -> None:
        self.failed: list[tuple[str, str]] = []

    def reading(self, device: str, value: Any) -> bool:
        return False

    def sensor_failed(self, device: str, failure: SensorFailure) -> None:
        self.failed.append((device, failure.reason))


def test_a_load_with_a_name_already_entered_enters_nothing() -> None:
    dt = Devtab(Kernel(VirtualClock()))
    dt.load(memory_map(["S1"], ["A1"]))
    with pytest.raises(DeviceError, match="already in Devtab: S1") as info:
        dt.load(memory_map(["S1", "S2"]))
    assert "S2" not in str(info.value)
    assert len(dt) == 2 and "S2" not in dt and [e.name for e in dt] == ["S1", "A1"]
    with pytest.raises(DeviceError, match="no device named 'S9' in Devtab"):
        dt.suspend("S9")


def test_the_link_set_after_construction_carries_commands_and_status_reports() -> None:
    k = Kernel(VirtualClock())
    dt = Devtab(k, local=[1])               # the map's devices are on machine 0: not ours
    dt.load(memory_map(["S1"], ["A1"]))
    with pytest.raises(DeviceError, match=r"A1 is on machine 0.*no link leads there"):
        dt.write("A1", 5.0, "T")
    remote = Remote()
    dt.remote = remote
    dt.write("A1", 5.0, "T")
    assert remote.commands == [("A1", 0, 5.0, "T")]
    assert dt.get("A1").value == 5.0

    local = Devtab(k)                       # every machine ours: status changes are told
    local.load(memory_map(["S1"]))
    local.remote = remote
    local.suspend("S1")
    assert remote.statuses == [("S1", DeviceStatus.SUSPENDED, "suspended by the host")]
    dt.set_status("S1", DeviceStatus.FAILED, "satellite 0 died")   # reported from there:
    assert len(remote.statuses) == 1                                # not told back
    assert not dt.healthy("S1")


def test_a_driver_failure_reaches_the_listener_and_the_health_listeners_once() -> None:
    k = Kernel(VirtualClock())
    dt = Devtab(k)
    dt.load(memory_map(["S1"]))
    listener = Listener()
    dt.listen(listener)
    heard: list[tuple[str, bool, str]] = []
    dt.add_health_listener(lambda d, ok, cause: heard.append((d, ok, cause)))
    dt.fail("S1", "wire cut")
    k.run()
    with pytest.raises(SensorFailure):
        dt.check_readable("S1")
    dt.recover("S1", "wire mended")
    k.run()
    dt.check_readable("S1")
    assert listener.failed == [("S1", "wire cut")]
    assert heard == [("S1", False, "wire cut"), ("S1", True, "wire mended")]
