"""Property-based checks of the scheduler's invariants (hypothesis).

1. Whenever a task is stepped, no ready task has a higher priority.
2. No message sent to a task is lost except by overwrite: for every link,
   sent == delivered + overwritten + (1 if a message is still unread), where sent is what the
   sender's ``put`` says the link took and delivered what the receiver's reads returned.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from chcos.devices.spec import DeviceMap
from chcos.errors import ReadTimeout
from chcos.kernel.clock import VirtualClock
from chcos.kernel.instrument import Instrument
from chcos.system.embedded import System
from chcos.tables.messages import InPort
from chcos.tables.tasks import TaskEntry, TaskState
from chcos.user.context import TaskContext

M = "vcan_tests.test_core_properties"

Op = tuple[str, float]
ops = st.lists(st.tuples(st.sampled_from(["sleep", "yield", "put", "read", "poll"]),
                         st.sampled_from([0.0, 0.01, 0.05, 0.1, 0.3])), min_size=1, max_size=25)


async def scripted(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    for op, arg in cmd["ops"]:
        if op == "sleep":
            await ctx.sleep(arg)
        elif op == "yield":
            await ctx.checkpoint()
        elif op == "put":
            cmd["put"] += ctx.put(ctx.now)
        elif op == "read" and ctx.inputs:
            with contextlib.suppress(ReadTimeout):
                await ctx.read_any(timeout=arg or 0.02)
                cmd["read"] += 1
        elif op == "poll" and ctx.inputs and ctx.poll(0, _NOTHING) is not _NOTHING:
            cmd["read"] += 1


_NOTHING = object()


class Checker(Instrument):
    def __init__(self, s: System) -> None:
        self.s = s
        self.violations: list[str] = []

    def before_step(self, task: TaskEntry) -> None:
        ready = self.s.kernel.ready_priorities()
        if ready and ready[0] > task.prio:
            self.violations.append(f"{task.name} p{task.prio} ran while p{ready[0]} ready")
        queued = self.s.kernel.ready_tasks()  # once each, and only READY
        if len({id(t) for t in queued}) != len(queued) or any(
                t.state is not TaskState.READY for t in queued):
            self.violations.append(f"ready queue {[(t.name, t.state.value) for t in queued]}")


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(programs=st.lists(ops, min_size=2, max_size=6),
       prios=st.lists(st.integers(0, 99), min_size=6, max_size=6))
def test_scheduler_invariants(programs: list[list[Op]], prios: list[int]) -> None:
    s = System(DeviceMap(), clock=VirtualClock(), machines=[0], base_dir=Path("."))
    chk = Checker(s)
    s.kernel.add_instrument(chk)
    # a chain: T0 at level 1, each next task reads the previous one (sensory links go up)
    names = [f"T{i}" for i in range(len(programs))]
    for i, name in enumerate(names):
        if i == 0:
            s.execute(f"install -m0 --code={M}:scripted {name}")
        else:
            s.execute(f"install -m0i1 --code={M}:scripted {name} {names[i - 1]}")
            s.execute(f"setpri -{prios[i]} {names[i - 1]} {name}")
    cmds = [{"ops": program, "put": 0, "read": 0} for program in programs]
    for i, name in enumerate(names):
        s.invoke(name, cmds[i], priority=prios[(i + 3) % len(prios)])
    s.run_for(30.0)
    assert chk.violations == [] and not s.kernel.dropped_instruments
    for i, name in enumerate(names[1:], start=1):
        link = s.msgtab.find(names[i - 1], name)
        port = link.port
        assert isinstance(port, InPort)
        unread = 1 if port.fresh else 0
        assert (link.sent, link.delivered) == (cmds[i - 1]["put"], cmds[i]["read"]), link
        assert link.sent == link.delivered + link.overwritten + unread, link
