"""support_cia402 - a CANopen master hosting a :class:`drivers.cia402.Axis` for the CiA 402 tests:
the canopen library's network on a python-can virtual channel, RPDO frames composed from an image
of every object they map (so a mode write never sends a stale controlword), TPDOs decoded into
readings, reads answered by SDO. It is the shape the CANopen driver takes when it hosts an axis.

Time is virtual: :meth:`Cia402Host.cycle` steps the drive by ``dt``, waits until the drive's
TPDOs have arrived (a condition, no sleep), feeds the axis one reading and sends what it returns,
waiting after each frame until the drive applied it.
"""

from __future__ import annotations

import struct
import threading
from collections.abc import Callable
from typing import Any, Protocol

import canopen

from drivers.cia402 import Actions, Axis, AxisConfig, Fault, Obj, Op, Reading, Result

WAIT = 10.0  # seconds to wait for a frame's effect before a test fails


class Drive(Protocol):
    """What the host needs from a simulated drive under test."""

    def step(self, dt: float) -> None: ...
    def published(self) -> tuple[int, int, int, int, int]: ...
    def frames(self) -> int: ...
    def wait(self, predicate: Callable[[], bool], timeout: float = 10.0) -> bool: ...


#: RPDOs of a typical vendor drive: (COB-ID base, mapped objects with struct formats)
RPDOS: dict[Obj, tuple[int, tuple[tuple[Obj, str], ...]]] = {
    Obj.CONTROLWORD: (0x200, ((Obj.CONTROLWORD, "H"),)),
    Obj.MODES: (0x300, ((Obj.CONTROLWORD, "H"), (Obj.MODES, "b"))),
    Obj.TARGET_POSITION: (0x400, ((Obj.CONTROLWORD, "H"), (Obj.TARGET_POSITION, "i"))),
    Obj.TARGET_VELOCITY: (0x500, ((Obj.CONTROLWORD, "H"), (Obj.TARGET_VELOCITY, "i"))),
}
#: SDO data formats of the objects an axis reads
READ_FORMATS = {Obj.STATUSWORD: "<H", Obj.MODES_DISPLAY: "<b", Obj.ERROR_CODE: "<H",
                Obj.POSITION_ACTUAL: "<i", Obj.VELOCITY_ACTUAL: "<i"}


class Cia402Host:
    """One axis on node ``node_id`` of virtual channel ``channel``, hosted as a driver would."""

    def __init__(self, channel: str, node_id: int, drive: Drive, config: AxisConfig,
                 dt: float = 0.01) -> None:
        self.node_id = node_id
        self.drive = drive
        self.axis = Axis(config)
        self.dt = dt
        self.now = 0.0
        self.image: dict[Obj, int] = {Obj.CONTROLWORD: 0, Obj.MODES: 0,
                                      Obj.TARGET_POSITION: 0, Obj.TARGET_VELOCITY: 0}
        self.results: list[Result] = []
        self.faults: list[Fault | None] = []
        self.emcys: list[int] = []
        self.sdo_reads: list[Obj] = []
        self._cond = threading.Condition()
        self._view: dict[str, int] = {}
        self.network: Any = canopen.Network()
        self.network.connect(interface="virtual", channel=channel, receive_own_messages=False)
        self.node: Any = canopen.RemoteNode(node_id, canopen.ObjectDictionary())
        self.network.add_node(self.node)
        self.network.subscribe(0x180 + node_id, self._on_tpdo1)
        self.network.subscribe(0x280 + node_id, self._on_tpdo2)
        self.network.subscribe(0x80 + node_id, self._on_emcy)

    def close(self) -> None:
        """Disconnect the network."""
        self.network.disconnect()

    def start_node(self) -> None:
        """NMT start; returns when the drive's first TPDOs arrived."""
        self.network.send_message(0x000, bytes([0x01, self.node_id]))
        self.settle()

    # -- receiving -----------------------------------------------------------------------------

    def _on_tpdo1(self, can_id: int, data: bytes, timestamp: float) -> None:
        sw, mode, err = struct.unpack("<HbH", bytes(data[:5]))
        with self._cond:
            self._view.update(statusword=sw, mode=mode, error=err)
            self._cond.notify_all()

    def _on_tpdo2(self, can_id: int, data: bytes, timestamp: float) -> None:
        pos, vel = struct.unpack("<ii", bytes(data[:8]))
        with self._cond:
            self._view.update(position=pos, velocity=vel)
            self._cond.notify_all()

    def _on_emcy(self, can_id: int, data: bytes, timestamp: float) -> None:
        (code,) = struct.unpack("<H", bytes(data[:2]))
        with self._cond:
            self.emcys.append(code)
            self._cond.notify_all()

    def _seen(self) -> tuple[int, ...] | None:
        v = self._view
        keys = ("statusword", "mode", "position", "velocity", "error")
        return tuple(v[k] for k in keys) if all(k in v for k in keys) else None

    def settle(self) -> None:
        """Wait until the TPDOs show what the drive publishes now."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._seen() == self.drive.published(), WAIT):
                raise AssertionError(f"TPDOs show {self._seen()}, the drive "
                                     f"{self.drive.published()}")

    def reading(self) -> Reading:
        """The last TPDO values as one reading."""
        with self._cond:
            v = dict(self._view)
        return Reading(statusword=v.get("statusword"), mode_display=v.get("mode"),
                       position=v.get("position"), velocity=v.get("velocity"),
                       error_code=v.get("error"))

    # -- sending -------------------------------------------------------------------------------

    def perform(self, actions: Actions) -> None:
        """Send the writes (one RPDO frame each, composed from the image, waiting until the drive
        applied it), answer the reads by SDO, and keep results and faults."""
        for write in actions.writes:
            self.image[write.obj] = write.value
            cob, layout = RPDOS[write.obj]
            data = b"".join(struct.pack("<" + fmt, self.image[obj]) for obj, fmt in layout)
            before = self.drive.frames()
            self.network.send_message(cob + self.node_id, data)
            if not self.drive.wait(lambda b=before: self.drive.frames() > b, WAIT):
                raise AssertionError(f"the drive did not apply {write}")
        self.results.extend(actions.results)
        self.faults.extend(actions.faults)
        if actions.reads:
            values: dict[str, int] = {}
            for obj in actions.reads:
                self.sdo_reads.append(obj)
                raw = self.node.sdo.upload(int(obj), 0)
                (values[obj.name],) = struct.unpack(READ_FORMATS[obj], bytes(raw))
            reading = Reading(statusword=values.get("STATUSWORD"),
                              mode_display=values.get("MODES_DISPLAY"),
                              error_code=values.get("ERROR_CODE"))
            self.perform(self.axis.update(reading, self.now))

    def cycle(self) -> None:
        """One cycle: the drive steps, its TPDOs arrive, the axis takes them and answers."""
        self.now = round(self.now + self.dt, 9)
        self.drive.step(self.dt)
        self.settle()
        self.perform(self.axis.update(self.reading(), self.now))

    def run(self, start: Callable[[float], Actions], limit: float = 60.0) -> Result:
        """Start a command (e.g. ``host.axis.enable``) and cycle until it ends; its result."""
        count = len(self.results)
        self.perform(start(self.now))
        end = self.now + limit
        while True:
            for result in self.results[count:]:
                if not result.reason.startswith("superseded"):
                    return result
            if self.now > end:
                raise AssertionError(f"no result within {limit} s of virtual time")
            self.cycle()

    def idle(self, seconds: float) -> None:
        """Cycle ``seconds`` of virtual time with no command."""
        end = self.now + seconds
        while self.now < end:
            self.cycle()

    def op_results(self, op: Op) -> list[Result]:
        """The results of ``op`` so far."""
        return [r for r in self.results if r.op is op]
