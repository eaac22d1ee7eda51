"""The simulated CANopen node against a master scripted on the wire: every NMT command, SDO
transfer and SYNC below is raw python-can frames written here (not canopen's client, not
chcos' driver), and the assertions are on the frames the node put on the bus - boot-up, NMT
states in its heartbeats, PDOs only when OPERATIONAL, configuration lost on reset unless stored,
0x1001 and EMCY on a fault, synchronous TPDOs per SYNC, answers for objects without a default,
and the heartbeat consumer's reaction to a silent master."""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import pytest

from chcos.apps.sim.canopen_slave import (
    SERVO_EDS,
    CanopenSlave,
    Clock,
    MasterLost,
    NmtState,
)
from chcos.errors import ConfigError
from vcan_tests.netutil import unique_channel
from vcan_tests.support_fb import WAIT

AWKWARD = Path(__file__).resolve().parent / "vendor" / "awkward_ax7.eds"
NODE = 3
MASTER = 0x7F


class Wire:
    """The master side: a raw python-can handle, frames kept in arrival order."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.seen: list[can.Message] = []

    def close(self) -> None:
        self.bus.shutdown()

    def send(self, cob: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))

    def nmt(self, command: int, node: int = NODE) -> None:
        self.send(0x000, bytes([command, node]))

    def sync(self) -> None:
        self.send(0x080, b"")

    def heartbeat(self, node: int = MASTER, state: int = 0x05) -> None:
        self.send(0x700 + node, bytes([state]))

    def expect(self, match: Callable[[can.Message], bool], what: str) -> can.Message:
        """The next frame that ``match``es (earlier ones are kept in ``seen``)."""
        while True:
            msg = self.bus.recv(WAIT)
            assert msg is not None, f"no {what} within {WAIT} s"
            self.seen.append(msg)
            if match(msg):
                return msg

    def drain(self) -> list[can.Message]:
        """Every frame already on the wire, without waiting."""
        out = []
        while (msg := self.bus.recv(0)) is not None:
            out.append(msg)
        self.seen.extend(out)
        return out

    def _sdo(self, request: bytes, node: int) -> bytes:
        self.send(0x600 + node, request)
        return bytes(self.expect(lambda m: m.arbitration_id == 0x580 + node,
                                 "SDO response").data)

    def upload(self, index: int, sub: int, node: int = NODE) -> bytes | int:
        """Expedited SDO upload: the data, or the abort code."""
        resp = self._sdo(struct.pack("<BHB4x", 0x40, index, sub), node)
        if resp[0] == 0x80:
            return int(struct.unpack_from("<I", resp, 4)[0])
        assert resp[0] & 0xE3 == 0x43, f"not an expedited upload response: {resp.hex()}"
        size = 4 - ((resp[0] >> 2) & 3)
        return resp[4:4 + size]

    def download(self, index: int, sub: int, data: bytes, node: int = NODE) -> int:
        """Expedited SDO download: 0 when confirmed, else the abort code."""
        cs = 0x23 | ((4 - len(data)) << 2)
        resp = self._sdo(struct.pack("<BHB", cs, index, sub) + data.ljust(4, b"\x00"), node)
        if resp[0] == 0x80:
            return int(struct.unpack_from("<I", resp, 4)[0])
        assert resp[0] == 0x60, f"not a download response: {resp.hex()}"
        return 0

    def barrier(self) -> list[can.Message]:
        """Wait until the node has handled every frame sent before (it answers SDO in order),
        and return what it sent meanwhile."""
        before = len(self.seen)
        self.upload(0x1000, 0)
        return [m for m in self.seen[before:] if m.arbitration_id != 0x580 + NODE]


@pytest.fixture
def wire() -> Iterator[tuple[Wire, str]]:
    channel = unique_channel("cosim")
    w = Wire(channel)
    try:
        yield w, channel
    finally:
        w.close()


def _slave(channel: str, eds: Path = SERVO_EDS, **kw: object) -> CanopenSlave:
    kw.setdefault("heartbeat_period", 0.1)
    kw.setdefault("clock", Clock.TICK)
    return CanopenSlave(NODE, eds, channel=channel, **kw)  # type: ignore[arg-type]


def _states(frames: list[can.Message]) -> list[int]:
    return [m.data[0] for m in frames if m.arbitration_id == 0x700 + NODE]


def test_boot_up_then_heartbeats_carry_the_nmt_state(wire: tuple[Wire, str]) -> None:
    w, channel = wire
    with _slave(channel) as slave:
        boot = w.expect(lambda m: m.arbitration_id == 0x700 + NODE, "boot-up")
        assert bytes(boot.data) == b"\x00"
        slave.tick(0.1)
        assert w.expect(lambda m: m.arbitration_id == 0x700 + NODE, "heartbeat").data[0] == 0x7F
        for command, state in ((0x01, 0x05), (0x02, 0x04), (0x80, 0x7F), (0x01, 0x05)):
            w.nmt(command)
            assert slave.wait_state(NmtState(state), WAIT)
            slave.tick(0.1)
            assert w.expect(lambda m: m.arbitration_id == 0x700 + NODE,
                            "heartbeat").data[0] == state
        w.nmt(0x02, node=NODE + 1)                  # for another node: ignored
        w.nmt(0x02, node=0)                         # broadcast: stops this one
        assert slave.wait_state(NmtState.STOPPED, WAIT)


def test_stopped_node_answers_no_sdo_and_sends_no_emcy(wire: tuple[Wire, str]) -> None:
    w, channel = wire
    with _slave(channel) as slave:
        w.nmt(0x02)
        assert slave.wait_state(NmtState.STOPPED, WAIT)
        w.send(0x600 + NODE, struct.pack("<BHB4x", 0x40, 0x1000, 0))
        slave.inject_fault(0x4210)
        w.nmt(0x80)
        assert slave.wait_state(NmtState.PRE_OPERATIONAL, WAIT)
        sent = w.barrier()
        assert [m for m in sent if m.arbitration_id in (0x580 + NODE, 0x80 + NODE)] == []
        assert w.upload(0x1001, 0) == b"\x09"      # generic + temperature, still set


def test_no_pdo_before_operational(wire: tuple[Wire, str]) -> None:
    w, channel = wire
    with _slave(channel) as slave:
        slave.set(0x6064, 0, 111)                  # TPDO1, event-driven
        w.send(0x200 + NODE, struct.pack("<i", 4242))     # RPDO1: target position
        sent = w.barrier()
        assert [m for m in sent if m.arbitration_id == 0x180 + NODE] == []
        assert w.upload(0x607A, 0) == struct.pack("<i", 0)
        slave.tick(0.2)                            # event timer due, but not OPERATIONAL
        assert [m for m in w.barrier() if m.arbitration_id == 0x180 + NODE] == []
        w.nmt(0x01)
        assert slave.wait_state(NmtState.OPERATIONAL, WAIT)
        slave.set(0x6064, 0, 222)
        tpdo = w.expect(lambda m: m.arbitration_id == 0x180 + NODE, "TPDO1")
        assert bytes(tpdo.data) == struct.pack("<i", 222)
        w.send(0x200 + NODE, struct.pack("<i", 4242))
        w.barrier()
        assert w.upload(0x607A, 0) == struct.pack("<i", 4242)


def test_reset_loses_configuration_unless_stored(wire: tuple[Wire, str]) -> None:
    w, channel = wire
    with _slave(channel, heartbeat_period=0) as slave:
        w.expect(lambda m: m.arbitration_id == 0x700 + NODE, "boot-up")
        assert w.download(0x1017, 0, struct.pack("<H", 50)) == 0
        assert w.download(0x6081, 0, struct.pack("<I", 777)) == 0
        w.nmt(0x81)                                # reset node
        assert bytes(w.expect(lambda m: m.arbitration_id == 0x700 + NODE,
                              "boot-up").data) == b"\x00"
        assert w.upload(0x1017, 0) == b"\x00\x00"          # EDS default again
        assert w.upload(0x6081, 0) == struct.pack("<I", 10000)
        # stored with the 'save' signature: survives reset node
        assert w.download(0x1017, 0, struct.pack("<H", 50)) == 0
        assert w.download(0x1010, 1, b"save") == 0
        assert w.download(0x1010, 1, b"nope") == 0x08000020   # wrong signature refused
        assert w.download(0x1017, 0, struct.pack("<H", 70)) == 0   # not stored
        w.nmt(0x81)
        w.expect(lambda m: m.arbitration_id == 0x700 + NODE, "boot-up")
        assert w.upload(0x1017, 0) == struct.pack("<H", 50)
        # reset communication keeps the application's values, reloads the communication's
        assert w.download(0x6081, 0, struct.pack("<I", 555)) == 0
        assert w.download(0x1017, 0, struct.pack("<H", 90)) == 0
        w.nmt(0x82)
        w.expect(lambda m: m.arbitration_id == 0x700 + NODE, "boot-up")
        assert w.upload(0x6081, 0) == struct.pack("<I", 555)
        assert w.upload(0x1017, 0) == struct.pack("<H", 50)
        # 'load' on 0x1011 drops what was stored, from the next reset on
        assert w.download(0x1011, 1, b"load") == 0
        w.nmt(0x81)
        w.expect(lambda m: m.arbitration_id == 0x700 + NODE, "boot-up")
        assert w.upload(0x1017, 0) == b"\x00\x00"
        assert slave.stats.boots == 5


def test_heartbeat_producer_follows_0x1017(wire: tuple[Wire, str]) -> None:
    w, channel = wire
    with _slave(channel, heartbeat_period=0) as slave:
        w.expect(lambda m: m.arbitration_id == 0x700 + NODE, "boot-up")
        slave.tick(1.0)
        assert _states(w.barrier()) == []           # no producer
        assert w.download(0x1017, 0, struct.pack("<H", 100)) == 0
        for _ in range(5):
            slave.tick(0.1)
        assert _states(w.barrier()) == [0x7F] * 5


def test_fault_sets_0x1001_and_sends_emcy_then_error_reset(wire: tuple[Wire, str]) -> None:
    w, channel = wire
    with _slave(channel, refuse_start_on_error=True) as slave:
        slave.inject_fault(0x3210, data=b"\x01\x02")          # DC link over-voltage
        emcy = w.expect(lambda m: m.arbitration_id == 0x80 + NODE, "EMCY")
        assert bytes(emcy.data) == bytes.fromhex("103205") + b"\x01\x02\x00\x00\x00"
        assert w.upload(0x1001, 0) == b"\x05"                   # generic + voltage
        w.nmt(0x01)                                             # refused while faulted
        slave.tick(0.1)
        assert _states(w.barrier()) == [0x7F]
        slave.clear_fault(0x3210)
        reset = w.expect(lambda m: m.arbitration_id == 0x80 + NODE, "error-reset EMCY")
        assert bytes(reset.data) == bytes(8)
        assert w.upload(0x1001, 0) == b"\x00"
        w.nmt(0x01)
        assert slave.wait_state(NmtState.OPERATIONAL, WAIT)


def test_fault_still_present_is_reported_again_after_a_reset(wire: tuple[Wire, str]) -> None:
    w, channel = wire
    with _slave(channel) as slave:
        slave.inject_fault(0x4310)
        w.expect(lambda m: m.arbitration_id == 0x80 + NODE, "EMCY")
        w.nmt(0x81)
        w.expect(lambda m: m.arbitration_id == 0x700 + NODE and m.data[0] == 0, "boot-up")
        again = w.expect(lambda m: m.arbitration_id == 0x80 + NODE, "EMCY after boot-up")
        assert struct.unpack_from("<HB", again.data) == (0x4310, 0x09)


def test_synchronous_tpdo_goes_out_on_every_nth_sync(wire: tuple[Wire, str]) -> None:
    w, channel = wire
    with _slave(channel, AWKWARD, heartbeat_period=0) as slave:
        w.nmt(0x01)
        assert slave.wait_state(NmtState.OPERATIONAL, WAIT)
        slave.set(0x6041, 0, 0x0237)
        slave.set(0x6064, 0, -5)
        slave.tick(1.0)                     # no event timer: nothing without SYNC
        assert [m for m in w.barrier() if m.arbitration_id == 0x180 + NODE] == []
        per_sync = []
        for _ in range(3):
            w.sync()
            per_sync.append([bytes(m.data) for m in w.barrier()
                             if m.arbitration_id == 0x180 + NODE])
        assert per_sync == [[struct.pack("<Hi", 0x0237, -5)]] * 3   # type 1: every SYNC
        w.nmt(0x80)
        assert w.download(0x1800, 2, b"\x03") == 0   # type 3: every third SYNC
        w.nmt(0x01)
        counts = []
        for _ in range(6):
            w.sync()
            counts.append(len([m for m in w.barrier() if m.arbitration_id == 0x180 + NODE]))
        assert counts == [0, 0, 1, 0, 0, 1]
        assert [p.trans_type for p in slave.tpdos][:1] == [3]


def test_acyclic_synchronous_tpdo_only_after_a_change(wire: tuple[Wire, str]) -> None:
    w, channel = wire
    with _slave(channel, AWKWARD, heartbeat_period=0) as slave:
        assert w.download(0x1800, 2, b"\x00") == 0
        w.nmt(0x01)
        assert slave.wait_state(NmtState.OPERATIONAL, WAIT)
        counts = []
        for value in (1, 1, 2, 2):
            slave.set(0x6064, 0, value)
            w.sync()
            counts.append(len([m for m in w.barrier() if m.arbitration_id == 0x180 + NODE]))
        assert counts == [1, 0, 1, 0]


def test_event_timer_tpdo_on_the_tick_clock(wire: tuple[Wire, str]) -> None:
    w, channel = wire
    with _slave(channel, AWKWARD, heartbeat_period=0) as slave:
        w.nmt(0x01)
        assert slave.wait_state(NmtState.OPERATIONAL, WAIT)
        slave.set(0x606C, 0, 9)                    # TPDO2: on change ...
        for _ in range(4):
            slave.tick(0.025)                      # ... and every 50 ms
        tpdo2 = [bytes(m.data) for m in w.barrier() if m.arbitration_id == 0x280 + NODE]
        assert tpdo2 == [struct.pack("<i", 9)] * 3


def test_objects_without_default_read_as_zero_of_their_type(wire: tuple[Wire, str]) -> None:
    w, channel = wire
    with _slave(channel, AWKWARD, heartbeat_period=0):
        assert w.upload(0x6064, 0) == bytes(4)      # INTEGER32, no DefaultValue
        assert w.upload(0x6060, 0) == bytes(1)      # INTEGER8
        assert w.upload(0x2000, 0) == bytes(2)      # INTEGER16, empty limits
        assert w.upload(0x6099, 0) == 0x06020000    # no such object: still an abort


def test_rpdos_sharing_the_controlword_each_write_it(wire: tuple[Wire, str]) -> None:
    w, channel = wire
    with _slave(channel, AWKWARD, heartbeat_period=0) as slave:
        w.nmt(0x01)
        assert slave.wait_state(NmtState.OPERATIONAL, WAIT)
        w.send(0x200 + NODE, struct.pack("<H", 0x000F))             # RPDO1: controlword
        w.barrier()
        assert slave.get(0x6040) == 0x000F
        w.send(0x300 + NODE, struct.pack("<Hb", 0x0002, 1))         # RPDO2: cw + mode
        w.barrier()
        assert (slave.get(0x6040), slave.get(0x6060)) == (0x0002, 1)


def test_silent_master_sends_node_to_pre_operational_and_calls_the_hook(
        wire: tuple[Wire, str]) -> None:
    w, channel = wire
    events: list[MasterLost] = []
    with _slave(channel, AWKWARD, heartbeat_period=0) as slave:
        slave.add_master_lost_hook(lambda s, e: events.append(e))
        assert w.download(0x1016, 1, struct.pack("<I", (MASTER << 16) | 200)) == 0
        w.nmt(0x01)
        assert slave.wait_state(NmtState.OPERATIONAL, WAIT)
        slave.tick(1.0)                 # no heartbeat seen yet: supervision not started
        assert slave.state is NmtState.OPERATIONAL
        for _ in range(5):
            w.heartbeat()
            w.barrier()
            slave.tick(0.1)
        assert slave.state is NmtState.OPERATIONAL and events == []
        slave.tick(0.15)                # 250 ms since the last one > 200 ms
        emcy = w.expect(lambda m: m.arbitration_id == 0x80 + NODE, "EMCY 0x8130")
        assert struct.unpack_from("<HB", emcy.data) == (0x8130, 0x11)
        assert slave.state is NmtState.PRE_OPERATIONAL
        assert events == [MasterLost(master=MASTER, timeout=0.2, abort_option=3)]
        assert w.upload(0x1001, 0) == b"\x11"
        w.heartbeat()                   # the master is back: error reset
        reset = w.expect(lambda m: m.arbitration_id == 0x80 + NODE, "error-reset EMCY")
        assert bytes(reset.data) == bytes(8)
        assert slave.state is NmtState.PRE_OPERATIONAL   # restarting is the master's job


@pytest.mark.parametrize(("behaviour", "state"), [(1, NmtState.OPERATIONAL),
                                                   (2, NmtState.STOPPED)])
def test_error_behaviour_0x1029_decides_the_state(wire: tuple[Wire, str], behaviour: int,
                                                  state: NmtState) -> None:
    w, channel = wire
    with _slave(channel, AWKWARD, heartbeat_period=0) as slave:
        assert w.download(0x1016, 1, struct.pack("<I", (MASTER << 16) | 100)) == 0
        assert w.download(0x1029, 1, bytes([behaviour])) == 0
        w.nmt(0x01)
        w.heartbeat()
        w.barrier()
        slave.tick(0.2)
        assert slave.wait_state(state, WAIT)
        assert slave.stats.masters_lost == 1


def test_servo_holds_its_position_when_the_master_is_lost(wire: tuple[Wire, str]) -> None:
    w, channel = wire
    with _slave(channel, heartbeat_period=0) as slave:
        assert w.download(0x6007, 0, struct.pack("<h", 3)) == 0       # quick stop
        assert w.download(0x1016, 1, struct.pack("<I", (MASTER << 16) | 100)) == 0
        assert w.download(0x6081, 0, struct.pack("<I", 1000)) == 0
        w.nmt(0x01)
        w.send(0x200 + NODE, struct.pack("<i", 5000))                 # RPDO1: target
        w.heartbeat()
        w.barrier()
        slave.tick(0.05)
        slave.tick(0.1)                                               # lost after 100 ms
        held = slave.get(0x6064)
        assert 0 < held < 5000 and slave.get(0x607A) == held
        for _ in range(10):
            slave.tick(0.1)
        assert slave.get(0x6064) == held


def test_realtime_heartbeat_and_restart_of_a_stopped_slave(wire: tuple[Wire, str]) -> None:
    w, channel = wire
    slave = _slave(channel, heartbeat_period=0.02, clock=Clock.REAL)
    slave.start()
    try:
        w.expect(lambda m: m.arbitration_id == 0x700 + NODE and m.data[0] == 0x7F,
                 "a heartbeat on real time")
        w.nmt(0x01)
        w.expect(lambda m: m.arbitration_id == 0x700 + NODE and m.data[0] == 0x05,
                 "an OPERATIONAL heartbeat")
        slave.stop()
        slave.start()                                 # a power cycle: boot-up again
        w.expect(lambda m: m.arbitration_id == 0x700 + NODE and m.data[0] == 0x00, "boot-up")
        assert slave.state is NmtState.PRE_OPERATIONAL
    finally:
        slave.stop()


def test_bad_fault_code_is_refused() -> None:
    slave = CanopenSlave(NODE, channel=unique_channel("cosim"))
    with pytest.raises(ConfigError, match="fault code 0x10: expected an EMCY error code"):
        slave.inject_fault(0x10)


def test_pdo_remapping_follows_the_cia301_procedure(wire: tuple[Wire, str]) -> None:
    w, channel = wire
    with _slave(channel, AWKWARD, heartbeat_period=0) as slave:
        assert w.download(0x1A00, 1, struct.pack("<I", 0x60400010)) == 0x08000022  # PDO valid
        assert w.download(0x1800, 1, struct.pack("<I", 0x1C3)) == 0x06090030   # new COB-ID
        assert w.download(0x1800, 1, struct.pack("<I", 0x8000_0183)) == 0      # disable
        assert w.download(0x1A00, 1, struct.pack("<I", 0x60400010)) == 0x08000022  # count 2
        assert w.download(0x1A00, 0, b"\x00") == 0
        assert w.download(0x1A00, 1, struct.pack("<I", 0x10000020)) == 0x06040041  # 0x1000
        assert w.download(0x1A00, 1, struct.pack("<I", 0x60990020)) == 0x06020000  # missing
        assert w.download(0x1A00, 1, struct.pack("<I", 0x60400010)) == 0
        assert w.download(0x1A00, 0, b"\x03") == 0x06040042     # more entries than exist
        assert w.download(0x1A00, 0, b"\x01") == 0
        assert w.download(0x1800, 1, struct.pack("<I", 0x183)) == 0            # enable
        assert w.download(0x1401, 1, struct.pack("<I", 0x8000_0303)) == 0
        assert w.download(0x1601, 0, b"\x00") == 0
        assert w.download(0x1601, 1, struct.pack("<I", 0x60410010)) == 0x06040041  # ro object
        w.nmt(0x01)
        assert slave.wait_state(NmtState.OPERATIONAL, WAIT)
        slave.set(0x6040, 0, 0x1234)
        w.sync()
        tpdo1 = [bytes(m.data) for m in w.barrier() if m.arbitration_id == 0x180 + NODE]
        assert tpdo1 == [struct.pack("<H", 0x1234)]          # the new mapping, 16 bits
        w.send(0x300 + NODE, struct.pack("<Hb", 7, 7))         # RPDO2 disabled: ignored
        w.barrier()
        assert slave.get(0x6060) == 0


def test_error_history_0x1003_and_emcy_cob_id_0x1014(wire: tuple[Wire, str]) -> None:
    w, channel = wire
    with _slave(channel, heartbeat_period=0) as slave:
        assert w.upload(0x1003, 0) == b"\x00"
        slave.inject_fault(0x3210)
        slave.inject_fault(0x4210)
        assert w.upload(0x1003, 0) == b"\x01"                    # the EDS holds one entry
        assert w.upload(0x1003, 1) == struct.pack("<I", 0x4210)  # newest first
        assert w.download(0x1003, 0, b"\x05") == 0x06090030
        assert w.download(0x1003, 0, b"\x00") == 0
        assert w.upload(0x1003, 1) == 0x08000024
        assert w.upload(0x1001, 0) == b"\x0D"                    # clearing history keeps 0x1001
        assert w.download(0x1014, 0, struct.pack("<I", 0x8000_0083)) == 0     # EMCY off
        before = slave.stats.emcys
        slave.clear_fault()
        assert [m for m in w.barrier() if 0x80 < m.arbitration_id < 0x100] == []
        assert slave.stats.emcys == before
