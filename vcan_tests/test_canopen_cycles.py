"""Tasks waiting for the SYNC cycle through the kernel (issue 36), against a durand node whose
TPDO1 (the position) is synchronous: ``await ctx.sync_cycle("co")`` wakes once per cycle with
its number and whether every synchronous TPDO of it arrived; an answer written to the node's
RPDO after SYNC n+1 is counted late (``sync-late-writes``); a node gone makes the cycles
incomplete; a bus without SYNC is refused. Virtual clock; what the node holds is asserted."""

from __future__ import annotations

from pathlib import Path

from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System
from chcos.tables.tasks import TaskState
from vcan_tests.netutil import unique_channel
from vcan_tests.peers.durand_node import DurandNode, Wire
from vcan_tests.support_canopen_system import NODE, write_devmap
from vcan_tests.support_faults import run_until

#: waits for ``count`` cycles of bus ``bus`` one after the other (the next one first), answers
#: each by writing its number to the node's target (RPDO1) and logs "number complete" (or
#: "error <text>") to the ``log`` file
TASK = '''
async def main(ctx, command):
    n = None
    with open(ctx.params["log"], "a", encoding="utf-8") as log:
        for _ in range(command["count"]):
            try:
                c = await ctx.sync_cycle(command["bus"], n)
                n = c.number + 1
            except Exception as exc:
                log.write(f"error {exc}\\n")
                log.flush()
                return
            try:
                ctx.write("target", c.number)
            except Exception as exc:     # the node failed meanwhile: the cycle still counts
                log.write(f"refused {exc}\\n")
            log.write(f"{c.number} {int(c.complete)}\\n")
            log.flush()
'''


def logged(path: Path) -> list[tuple[int, bool]]:
    if not path.exists():
        return []
    return [(int(a), b == "1") for a, b in (line.split() for line in
                                            path.read_text(encoding="utf-8").splitlines()
                                            if line[0].isdigit())]


def system(tmp_path: Path, node: DurandNode, sync_period: float = 0.01) -> System:
    tasks = tmp_path / "tasks"
    tasks.mkdir()
    (tasks / "answer.py").write_text(TASK, encoding="utf-8")
    s = System([write_devmap(tmp_path, node, sync_period)], clock=VirtualClock(),
               machines=[0], task_path=[tasks])
    log = tmp_path / "cycles.log"
    s.execute(f"install -m0i1o1 --param=log={str(log)!r} answer pos target".replace("'", '"'))
    return s


def why(s: System, log: Path) -> str:
    """The task's log and last error, for a failed assertion."""
    text = log.read_text(encoding="utf-8") if log.exists() else "(no log)"
    return f"{text[-2000:]}\nlast error: {s.tsktab.get('answer').last_error}"


def answers(wire: Wire) -> set[int]:
    """The values RPDO1 (the target) carried on the wire."""
    return {int.from_bytes(f.data[:4], "little", signed=True) for f in wire.of(0x200 + NODE)}


def late_writes(s: System) -> int:
    return int(s.devtab.bus_stats["co"].counts.get("sync-late-writes", 0))


def test_a_task_waits_for_each_cycle_and_its_answers_reach_the_node(tmp_path: Path) -> None:
    node = DurandNode(unique_channel("cyc"), NODE)
    wire = Wire(node.channel)
    s = system(tmp_path, node)
    log = tmp_path / "cycles.log"
    try:
        assert run_until(s, lambda: s.devtab.get("target").status.value == "OK")
        s.devtab.write("target", -7)                 # a host's write answers no cycle
        assert run_until(s, lambda: node.read(0x607A) == -7)
        assert late_writes(s) == 0
        s.invoke("answer", {"bus": "co", "count": 400})
        assert run_until(s, lambda: sum(c for _, c in logged(log)) >= 5), why(s, log)
        got = logged(log)
        numbers = [n for n, _ in got]
        assert numbers == list(range(numbers[0], numbers[0] + len(numbers)))   # every cycle once
        complete = s.devtab.bus_status()["co"]["sync"]["complete"]
        # the driver counted them complete too (at SYNC n+1: the last one may not be yet)
        assert sum(c for _, c in got) <= complete + 1
        # what the node saw: the answers, in its RPDO1, the last one in its object dictionary
        assert run_until(s, lambda: node.read(0x607A) >= numbers[-1])
        assert wire.wait_for(lambda w: set(numbers) <= answers(w))
        on_time_late = late_writes(s)
        # the kernel held up past SYNC n+2: the answer to cycle n goes out late, and is counted
        waiting = s.tsktab.get("answer")
        assert run_until(s, lambda: waiting.state is TaskState.WAITING)
        syncs = len(wire.of(0x080))
        assert wire.wait_for(lambda w: len(w.of(0x080)) >= syncs + 3)
        answered = len(logged(log))
        assert run_until(s, lambda: len(logged(log)) > answered and late_writes(s) > on_time_late)
        held_for = logged(log)[answered][0]
        assert node.wait(lambda: node.read(0x607A) >= held_for)
        # the node gone: its synchronous TPDO is missing, the cycles the task gets incomplete
        node.power_off()
        gone = len(logged(log))
        assert run_until(s, lambda: sum(1 for _, c in logged(log)[gone:] if not c) >= 5)
        status = s.devtab.bus_status()["co"]["sync"]
        assert status["missing"] >= 5 and status["late_writes"] >= 1
    finally:
        s.shutdown()
        wire.close()
        node.close()


def test_waiting_for_a_bus_without_a_cycle_is_refused(tmp_path: Path) -> None:
    node = DurandNode(unique_channel("cyc"), NODE)
    s = system(tmp_path, node)
    log = tmp_path / "cycles.log"
    try:
        s.invoke("answer", {"bus": "nowhere", "count": 1})
        assert run_until(s, lambda: log.exists() and "error" in log.read_text("utf-8"))
        assert "sync_cycle: no bus 'nowhere' driven by this process" in log.read_text("utf-8")
    finally:
        s.shutdown()
        node.close()


def test_each_cycle_is_told_once_in_order_as_soon_as_it_is_known() -> None:
    """The driver's side of the seam (drivers.canopen_sync), SYNCs observed as on SocketCAN:
    a cycle whose TPDO arrived is told complete at once, one without it when SYNC n+1 is seen,
    and nothing twice."""
    from drivers.canopen_sync import SyncCycle

    sync = SyncCycle(0.01, lambda: None, lambda text: None, "test-sync")
    sync.expect(0x185, 1)
    sync.start(produce=False)
    told: list[tuple[int, bool]] = []
    unwatch = sync.watch(lambda n, complete: told.append((n, complete)))
    sync.seen(0.00)                      # SYNC 1
    sync.tpdo(0x185)                     # its TPDO: cycle 1 complete now
    assert told == [(1, True)]
    sync.seen(0.01)                      # SYNC 2 closes cycle 1: told already
    sync.seen(0.02)                      # SYNC 3: cycle 2 had no TPDO
    assert told == [(1, True), (2, False)]
    sync.tpdo(0x185)
    sync.tpdo(0x185)                     # a second copy in the same cycle: told once
    unwatch()
    sync.seen(0.03)
    assert told == [(1, True), (2, False), (3, True)]
    assert sync.stats().complete == 2 and sync.stats().missing == 1
    sync.stop()
