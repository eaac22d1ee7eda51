"""test_cia402_stale_readings - the CANopen driver's axis host (drivers/canopen_axis.py) taking
readings in the order the wire gave them, not the order its I/O thread got round to them: a TPDO
that arrived during an SDO read waits in the queue behind the answer, and is older than it. The
two-process run of issue 37 (chcos run against chcos sim --from): ``mover`` enabled the axis
(confirmed OPERATION_ENABLED), then ``move_to`` failed at once with "the drive left
OPERATION_ENABLED for SWITCHED_ON (statusword 0x0233)". The queue and the reader thread are
played explicitly here (deterministic, no threads)."""

from __future__ import annotations

from typing import Any

from drivers.canopen_axis import AxisCall, AxisHost
from drivers.codecs.cia402 import AxisConfig, Mode, Obj, Op, Result, State, Write


class Rig:
    """An axis host with the driver's callbacks recorded, a queue of TPDO feeds as the I/O
    thread's, and SDO reads answered by ``answers`` (during which ``arriving`` TPDOs are
    received by the "reader thread")."""

    def __init__(self) -> None:
        self.sent: list[Write] = []
        self.queue: list[tuple[dict[Obj, int], int]] = []
        self.answers: dict[Obj, int] = {}
        self.arriving: list[dict[Obj, int]] = []
        self.reports: list[str] = []
        self.host = AxisHost("x", 1, AxisConfig("x", position_window=2), Mode.PP,
                             send=self.sent.append, read=self._read, deliver=lambda _v: None,
                             fail=lambda *_a: None, recover=lambda *_a: None,
                             report=self.reports.append)

    def tpdo(self, values: dict[Obj, int]) -> None:
        """The reader thread: a TPDO arrives, is marked and queued for the I/O thread."""
        self.queue.append((values, self.host.pdo_received(tuple(values))))

    def _read(self, obj: Obj, index: int) -> int | None:
        for values in self.arriving:          # frames the drive sent before its answer
            self.tpdo(values)
        self.arriving.clear()
        return self.answers.get(obj)

    def drain(self, now: float) -> None:
        """The I/O thread takes the queued TPDOs, in order."""
        while self.queue:
            values, mark = self.queue.pop(0)
            self.host.reading(values, now, mark)

    def controlwords(self) -> list[int]:
        return [w.value for w in self.sent if w.obj is Obj.CONTROLWORD]


def test_a_tpdo_that_arrived_during_an_sdo_read_never_takes_the_axis_back() -> None:
    rig = Rig()
    host = rig.host
    results: list[Result | Exception] = []

    def enabled(outcome: Result | Exception) -> None:
        results.append(outcome)
        # the mover task: enable confirmed, move at once (as ctx calls do)
        host.command(AxisCall(Op.MOVE_TO, 50.0), results.append, 0.2)

    rig.tpdo({Obj.STATUSWORD: 0x0250, Obj.MODES_DISPLAY: 1, Obj.POSITION_ACTUAL: 0})
    rig.drain(0.0)
    host.command(AxisCall(Op.ENABLE), enabled, 0.0)
    rig.tpdo({Obj.STATUSWORD: 0x0231})
    rig.drain(0.01)
    rig.tpdo({Obj.STATUSWORD: 0x0233})
    rig.drain(0.02)
    assert rig.controlwords() == [0x06, 0x07, 0x0F]
    # the node's heartbeat came back: the axis is read by SDO. The drive answers operation
    # enabled; a TPDO it sent before that answer (switched on) arrives during the read
    rig.answers = {Obj.STATUSWORD: 0x0237, Obj.MODES_DISPLAY: 1, Obj.POSITION_ACTUAL: 0}
    rig.arriving = [{Obj.STATUSWORD: 0x0233}]
    host.refresh(0.03)
    # the answer was asked before that TPDO arrived: dropped for the statusword; the engine,
    # whose statusword predates its last controlword, asks again, and that answer (newer than
    # the TPDO) confirms the enable; the mover's move starts
    assert [getattr(r, "op", r) for r in results] == [Op.ENABLE]
    assert host.status().busy is Op.MOVE_TO
    # the queued TPDO is taken now: older than the statusword held, it is ignored
    rig.drain(0.03)
    assert host.status().state is State.OPERATION_ENABLED and host.status().busy is Op.MOVE_TO
    assert host.engine.stale_readings >= 1 and len(results) == 1
    rig.tpdo({Obj.STATUSWORD: 0x1237, Obj.POSITION_ACTUAL: 20})        # set-point acked
    rig.drain(0.25)                                                    # bit 4 dropped
    rig.tpdo({Obj.STATUSWORD: 0x0637, Obj.POSITION_ACTUAL: 50})        # target reached
    rig.drain(0.3)
    outcomes: list[Any] = [(r.op, r.ok) if isinstance(r, Result) else r for r in results]
    assert outcomes == [(Op.ENABLE, True), (Op.MOVE_TO, True)], results
    assert rig.controlwords()[-2:] == [0x1F, 0x0F] and not rig.reports


def test_a_tpdo_queued_behind_an_sdo_answer_that_is_older_is_not_applied() -> None:
    """The other order: the answer came first on the wire and a TPDO with an older state was
    received before the I/O thread applied it; the TPDO sent after it wins, whatever the queue."""
    rig = Rig()
    host = rig.host
    rig.tpdo({Obj.STATUSWORD: 0x0637, Obj.MODES_DISPLAY: 1})
    old = rig.queue.pop()
    rig.tpdo({Obj.STATUSWORD: 0x0233})
    newer = rig.queue.pop()
    host.reading(*newer[:1], 0.1, newer[1])
    host.reading(*old[:1], 0.2, old[1])
    assert host.status().state is State.SWITCHED_ON and host.engine.stale_readings == 1
