"""canopen_slave - a simulated CANopen servo drive: a canopen ``LocalNode`` on a python-can bus.

canopen's ``LocalNode`` answers SDO and NMT but neither transmits TPDOs nor applies received RPDOs
to its object dictionary; :class:`CanopenSlave` adds both, plus a heartbeat producer that can be
stopped (to simulate loss), EMCY on demand, injected SDO aborts and a servo position loop stepped
by :meth:`CanopenSlave.tick` (virtual time) or by a real-time thread
(:meth:`CanopenSlave.run_realtime`, used by ``chcos sim canopen``).

canopen's own objects are held as ``Any``: the library is only partly typed.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError

from chcos import resources
from chcos.errors import BusError, ConfigError

#: The EDS shipped for the simulated servo drive.
SERVO_EDS = resources.path("chcos.apps.sim", "eds", "servo_drive.eds")

POSITION_ACTUAL = (0x6064, 0)
VELOCITY_ACTUAL = (0x606C, 0)
TARGET_POSITION = (0x607A, 0)
PROFILE_VELOCITY = (0x6081, 0)
STATUSWORD = (0x6041, 0)
HEARTBEAT_TIME = (0x1017, 0)

#: Statusword: ready to switch on, switched on, operation enabled, voltage enabled, quick stop off.
STATUS_ENABLED = 0x0037
#: Statusword bit 10: target reached.
STATUS_TARGET_REACHED = 0x0400


@dataclass
class ServoAxis:
    """The position loop of the simulated drive: position moves toward target at most ``max_speed``
    counts per second. Pure arithmetic; :meth:`step` never raises."""

    position: float = 0.0
    velocity: float = 0.0

    def step(self, target: int, max_speed: float, dt: float) -> None:
        """Advance ``dt`` seconds toward ``target``."""
        if dt <= 0:
            self.velocity = 0.0
            return
        error = target - self.position
        reach = max(0.0, max_speed) * dt
        move = max(-reach, min(reach, error))
        self.position += move
        self.velocity = move / dt


class CanopenSlave:
    """One simulated servo drive on a CAN bus.

    ``interface``/``channel``/``bitrate`` open a python-can bus (``virtual`` in tests). The
    heartbeat is produced every ``heartbeat_period`` seconds of real time (0: none). TPDOs go out
    when a mapped value changes and every event-timer period of the EDS (``tpdo_period`` overrides
    it), counted on the :meth:`tick` clock. Every method is thread-safe.
    """

    def __init__(self, node_id: int, eds: str | Path = SERVO_EDS, *, channel: str,
                 interface: str = "virtual", bitrate: int | None = None,
                 heartbeat_period: float = 0.1, tpdo_period: float | None = None) -> None:
        if not 1 <= node_id <= 127:
            raise ConfigError(f"canopen slave: node id {node_id} is not in 1..127")
        try:
            od = canopen.import_od(str(eds), node_id)
        except Exception as exc:  # canopen raises many types for a bad EDS
            raise ConfigError(f"canopen slave node {node_id}: cannot read EDS {eds}: {exc}") \
                from exc
        self.node_id = node_id
        self.eds = Path(eds)
        self._bus_args: dict[str, Any] = {"interface": interface, "channel": channel}
        if bitrate is not None:
            self._bus_args["bitrate"] = bitrate
        self._heartbeat_period = heartbeat_period
        self._tpdo_period = tpdo_period
        self._lock = threading.RLock()
        self._network: Any = canopen.Network()
        self._network.NOTIFIER_CYCLE = 0.05  # bounds how long stop() waits for the notifier
        self._node: Any = canopen.LocalNode(node_id, od)
        self._axis = ServoAxis()
        self._since_tpdo = 0.0
        self._aborts: dict[tuple[int, int], int] = {}
        self._started = False
        self._rt_stop = threading.Event()
        self._rt_thread: threading.Thread | None = None
        self._nmt_changed = threading.Condition()
        #: Set whenever an RPDO has been applied to the object dictionary.
        self.rpdo_received = threading.Event()

    # -- life cycle ---------------------------------------------------------------------------

    def start(self) -> None:
        """Open the bus, send the boot-up message, enter PRE-OPERATIONAL and start the heartbeat.
        Raises :class:`chcos.errors.BusError` if the bus cannot be opened."""
        with self._lock:
            if self._started:
                return
            try:
                self._network.connect(**self._bus_args)
            except (can.CanError, OSError, ValueError) as exc:
                raise BusError(f"canopen slave node {self.node_id}: cannot open CAN bus "
                               f"{self._bus_args}: {exc}") from exc
            self._network.add_node(self._node)
            node = self._node
            node.add_read_callback(self._on_sdo_read)
            node.tpdo.read(from_od=True)
            node.rpdo.read(from_od=True)
            for pdo_map in node.rpdo.map.values():
                pdo_map.add_callback(self._on_rpdo)
            node.data_store.setdefault(HEARTBEAT_TIME[0], {})[HEARTBEAT_TIME[1]] = \
                node.object_dictionary[0x1017].encode_raw(int(self._heartbeat_period * 1000))
            node.nmt.state = "INITIALISING"
            node.nmt.state = "PRE-OPERATIONAL"
            # A master's NMT start answering the boot-up can land between the two lines above;
            # canopen then starts no heartbeat (it does so only on INITIALISING -> PRE-OP), and
            # the node would sit silent in PRE-OPERATIONAL. Start it here whatever the order.
            if self._heartbeat_period > 0:
                node.nmt.start_heartbeat(int(self._heartbeat_period * 1000))
            self._network.subscribe(0, self._on_nmt)
            self._started = True

    def stop(self) -> None:
        """Stop the real-time thread, the heartbeat and the bus. Idempotent; never raises."""
        self.stop_realtime()
        with self._lock:
            if not self._started:
                return
            self._started = False
            try:
                self._node.nmt.stop_heartbeat()
                self._network.disconnect()
            except Exception:  # stop must not raise; the bus is going away anyway
                pass

    def __enter__(self) -> CanopenSlave:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- object dictionary --------------------------------------------------------------------

    def get(self, index: int, subindex: int = 0) -> Any:
        """The decoded value of object ``index:subindex``; raises :class:`ConfigError` if the EDS
        has no such object."""
        with self._lock:
            return self._var(index, subindex).decode_raw(self._stored(index, subindex))

    def set(self, index: int, subindex: int, value: Any) -> None:
        """Set object ``index:subindex`` as the device would (no access check); a change of a
        TPDO-mapped object sends that TPDO at once when OPERATIONAL. Raises :class:`ConfigError`
        for an object the EDS lacks."""
        with self._lock:
            data = self._var(index, subindex).encode_raw(value)
            old = self._node.data_store.get(index, {}).get(subindex)
            self._node.data_store.setdefault(index, {})[subindex] = data
            if old != data:
                self._send_tpdos_mapping(index, subindex)

    @property
    def nmt_state(self) -> str:
        """The node's NMT state (``'OPERATIONAL'``, ``'PRE-OPERATIONAL'``...)."""
        return str(self._node.nmt.state)

    def wait_state(self, state: str, timeout: float) -> bool:
        """Block until the NMT state is ``state`` (e.g. ``'OPERATIONAL'``); False on timeout."""
        with self._nmt_changed:
            return self._nmt_changed.wait_for(lambda: self.nmt_state == state, timeout)

    # -- fault injection ----------------------------------------------------------------------

    def stop_heartbeat(self) -> None:
        """Stop producing heartbeats (simulates a lost node; SDO and PDO keep working)."""
        self._node.nmt.stop_heartbeat()

    def start_heartbeat(self, period: float | None = None) -> None:
        """Resume heartbeats every ``period`` seconds (default: the constructor's period)."""
        if period is not None:
            self._heartbeat_period = period
        self._node.nmt.start_heartbeat(int(self._heartbeat_period * 1000))

    def send_emcy(self, code: int, register: int = 0, data: bytes = b"") -> None:
        """Send one EMCY frame (``code`` 0 is an error reset)."""
        if code == 0:
            self._node.emcy.reset(register, data)
        else:
            self._node.emcy.send(code, register, data)

    def inject_sdo_abort(self, index: int, subindex: int, code: int) -> None:
        """Answer every SDO read of ``index:subindex`` with abort ``code`` until cleared."""
        with self._lock:
            self._aborts[(index, subindex)] = code

    def clear_sdo_abort(self, index: int, subindex: int) -> None:
        """Undo :meth:`inject_sdo_abort`."""
        with self._lock:
            self._aborts.pop((index, subindex), None)

    # -- simulation ---------------------------------------------------------------------------

    def tick(self, dt: float) -> None:
        """Advance the servo and the TPDO event timers by ``dt`` seconds."""
        with self._lock:
            target = int(self.get(*TARGET_POSITION))
            speed = float(self.get(*PROFILE_VELOCITY))
            self._axis.step(target, speed, dt)
            position = round(self._axis.position)
            self.set(*VELOCITY_ACTUAL, round(self._axis.velocity))
            status = STATUS_ENABLED | (STATUS_TARGET_REACHED if position == target else 0)
            self.set(*STATUSWORD, status)
            self.set(*POSITION_ACTUAL, position)
            self._since_tpdo += dt
            period = self._tpdo_event_period()
            if period is not None and self._since_tpdo >= period:
                self._since_tpdo = 0.0
                for pdo_map in self._node.tpdo.map.values():
                    self._transmit(pdo_map)

    def run_realtime(self, step: float = 0.01) -> None:
        """Start a thread calling :meth:`tick` every ``step`` seconds of real time."""
        if self._rt_thread is not None:
            return
        self._rt_stop.clear()

        def loop() -> None:
            last = time.monotonic()
            while not self._rt_stop.wait(step):
                now = time.monotonic()
                self.tick(now - last)
                last = now

        self._rt_thread = threading.Thread(target=loop, name=f"canopen-slave-{self.node_id}",
                                           daemon=True)
        self._rt_thread.start()

    def stop_realtime(self) -> None:
        """Stop the :meth:`run_realtime` thread, if any."""
        thread, self._rt_thread = self._rt_thread, None
        if thread is not None:
            self._rt_stop.set()
            thread.join(timeout=2.0)

    # -- internals ----------------------------------------------------------------------------

    def _var(self, index: int, subindex: int) -> Any:
        var = self._node.object_dictionary.get_variable(index, subindex)
        if var is None:
            raise ConfigError(f"canopen slave node {self.node_id}: no object "
                              f"0x{index:04X}:{subindex:02X} in {self.eds}")
        return var

    def _stored(self, index: int, subindex: int) -> bytes:
        """The object's bytes as the SDO server would answer, without injected aborts."""
        stored = self._node.data_store.get(index, {}).get(subindex)
        if stored is not None:
            return bytes(stored)
        var = self._var(index, subindex)
        default = var.value if var.value is not None else var.default
        return bytes(var.encode_raw(default if default is not None else 0))

    def _tpdo_event_period(self) -> float | None:
        if self._tpdo_period is not None:
            return self._tpdo_period
        timers = [m.event_timer for m in self._node.tpdo.map.values()
                  if m.enabled and m.event_timer]
        return min(timers) / 1000.0 if timers else None

    def _send_tpdos_mapping(self, index: int, subindex: int) -> None:
        for pdo_map in self._node.tpdo.map.values():
            if any(v.index == index and v.subindex == subindex for v in pdo_map.map):
                self._transmit(pdo_map)

    def _transmit(self, pdo_map: Any) -> None:
        if not (self._started and pdo_map.enabled and self.nmt_state == "OPERATIONAL"):
            return
        for var in pdo_map.map:
            var.set_data(self._stored(var.index, var.subindex))
        # A send error (full queue at shutdown) is not fatal: the next change or timer resends.
        with contextlib.suppress(can.CanError):
            pdo_map.transmit()

    def _on_nmt(self, can_id: int, data: bytes, timestamp: float) -> None:
        with self._nmt_changed:
            self._nmt_changed.notify_all()

    def _on_rpdo(self, pdo_map: Any) -> None:
        if self.nmt_state != "OPERATIONAL":
            return
        with self._lock:
            for var in pdo_map.map:
                self._node.set_data(var.index, var.subindex, bytes(var.get_data()))
        self.rpdo_received.set()

    def _on_sdo_read(self, *, index: int, subindex: int, od: Any) -> None:
        code = self._aborts.get((index, subindex))
        if code is not None:
            raise SdoAbortedError(code)


def main(argv: Sequence[str] | None = None) -> int:
    """``chcos sim canopen``: run a simulated servo drive in real time until interrupted or
    ``--duration`` elapses. Returns the process exit status (0 ok, 2 bad arguments or bus)."""
    parser = argparse.ArgumentParser(prog="chcos sim canopen",
                                     description="Simulated CANopen servo drive (LocalNode).")
    parser.add_argument("--node", type=int, default=1, help="node id 1..127 (default 1)")
    parser.add_argument("--eds", default=str(SERVO_EDS), help="EDS file (default: servo_drive)")
    parser.add_argument("--interface", default="virtual", help="python-can interface")
    parser.add_argument("--channel", required=True, help="python-can channel (e.g. vcan0)")
    parser.add_argument("--bitrate", type=int, default=None)
    parser.add_argument("--heartbeat", type=float, default=0.1, help="heartbeat period, s")
    parser.add_argument("--step", type=float, default=0.01, help="physics step, s")
    parser.add_argument("--duration", type=float, default=None, help="run this long, s")
    args = parser.parse_args(list(argv) if argv is not None else None)
    try:
        slave = CanopenSlave(args.node, args.eds, channel=args.channel,
                             interface=args.interface, bitrate=args.bitrate,
                             heartbeat_period=args.heartbeat)
        slave.start()
    except (ConfigError, BusError) as exc:
        print(f"chcos sim canopen: {exc}", file=sys.stderr)
        return 2
    slave.run_realtime(args.step)
    print(f"canopen servo node {args.node} on {args.interface}:{args.channel}", flush=True)
    done = threading.Event()
    try:
        done.wait(args.duration)
    except KeyboardInterrupt:
        pass
    finally:
        slave.stop()
    return 0
