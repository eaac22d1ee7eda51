"""context - the user API: what a task's code calls (the thesis' Usrmgr.h / sysfile.h).

Every task function is ``async def task(ctx: TaskContext, command) -> result``; it runs once per
command (invocation) and its return is the normal completion (teotsk) reported to the owner.
``ctx`` is the task's Usrtab: eight input ports (sensory sources) and eight output ports (command
destinations), addressed by index or by the peer's name. Calls that can wait are awaited; sending
upward and writing to actuators never block.

Thesis name → chcos name: tgetc → :meth:`TaskContext.read` / :meth:`~TaskContext.read_any` /
:meth:`~TaskContext.poll`; tputc → :meth:`~TaskContext.put`; putc (actuator) →
:meth:`~TaskContext.write`; topen → :meth:`~TaskContext.invoke`;
tclose → :meth:`~TaskContext.close`;
teotsk → return, or :meth:`~TaskContext.complete`; msgstat → :meth:`~TaskContext.status`;
sleep → :meth:`~TaskContext.sleep`; gettid → :attr:`~TaskContext.tid`. A CiA 402 axis:
:meth:`~TaskContext.axis` (:mod:`chcos.user.axes`).
"""

from __future__ import annotations

import types
from collections.abc import Callable, Generator
from pathlib import Path
from typing import Any

from chcos.errors import MessageError
from chcos.kernel.scheduler import BLOCK, YIELD
from chcos.tables.messages import LinkType
from chcos.tables.tasks import TaskState
from chcos.user.axes import AxisHandle, axis_handle
from chcos.user.commanding import Commanding
from chcos.user.cycles import Cycle, wait_cycle
from chcos.user.ports import Port
from chcos.user.reading import Event, EventKind, Reading
from chcos.user.worldmodel import WorldModel

__all__ = ["Cycle", "Event", "EventKind", "Port", "TaskContext"]


class TaskContext(Reading, Commanding):
    """The handle a task's code uses for every system call. One per task, made at install.
    Its calls come in parts: :class:`~chcos.user.reading.Reading` (input ports, ``wait_any``,
    the exception tap), :class:`~chcos.user.commanding.Commanding` (output, commands, estop)."""

    # ---- identity ---------------------------------------------------------------------------
    @property
    def tid(self) -> int:
        """This task's id (gettid)."""
        return self._t.tid

    @property
    def name(self) -> str:
        """This task's name."""
        return self._t.name

    @property
    def machine(self) -> int:
        """The machine (satellite) number the task runs on."""
        return self._t.machine

    @property
    def level(self) -> int:
        """The task's level in the hierarchy (1 = just above the devices)."""
        return self._t.level

    @property
    def params(self) -> dict[str, Any]:
        """Install-time parameters (``install --param key=value``)."""
        return self._t.params

    @property
    def command(self) -> Any:
        """The command (parameters) of the current activation; after :meth:`take_command`, the
        newest one taken."""
        return self._t.command

    @property
    def has_command(self) -> bool:
        """True when the owner sent a newer command to this running activation (a repeated
        topen from the owner, Appendix 3) that :meth:`take_command` has not taken yet."""
        return self._t.new_command is not None

    @property
    def world(self) -> WorldModel:
        """This task's world model."""
        wm = self._t.world
        if not isinstance(wm, WorldModel):
            raise MessageError(f"task {self._t.name} has no world model")
        return wm

    @property
    def now(self) -> float:
        """The kernel clock's time in seconds."""
        return self._k.clock.now()

    @property
    def priority(self) -> int:
        """The priority the task runs at now."""
        return self._t.prio

    # ---- events -----------------------------------------------------------------------------
    def watch_events(self, fn: Callable[[str, str], None]) -> Callable[[], None]:
        """Call ``fn(kind, detail)`` on every system event (installs, setpri, invokes,
        completions, abnormal completions, pre-emptions, restarts, suspends, e-stops, device
        failures...) until the returned function is called. ``fn`` runs on the kernel thread in
        whatever step caused the event: it must not block (a system driver's log, e.g.)."""
        from chcos.kernel.instrument import Instrument

        class _Watch(Instrument):
            def event(self, kind: str, detail: str) -> None:
                fn(kind, detail)

        watch = _Watch()
        self._k.add_instrument(watch)
        return lambda: self._k.remove_instrument(watch)

    # ---- task management --------------------------------------------------------------------
    @types.coroutine
    def sleep(self, seconds: float) -> Generator[Any, Any, None]:
        """Sleep ``seconds`` of kernel-clock time (ASLEEP). Raises ValueError if negative."""
        if seconds < 0:
            raise ValueError(f"cannot sleep a negative time ({seconds})")
        t, k = self._t, self._k
        t.sleep_until = k.clock.now() + seconds

        def wake() -> None:
            t.timer = None
            k.wake(t, t.base_prio)

        t.timer = k.call_at(t.sleep_until, wake)
        k.block(t, TaskState.ASLEEP)
        yield BLOCK

    def sync_cycle(self, bus: str, n: int | None = None,
                   timeout: float | None = None) -> Generator[Any, Any, Cycle]:
        """Wait (through the kernel) for SYNC cycle ``n`` of field bus ``bus`` - the next one
        if None - to be over: a :class:`~chcos.user.cycles.Cycle` with ``complete`` True when
        every synchronous TPDO due in it arrived, False when SYNC n+1 went out first. RPDO
        writes made in answer that go out after SYNC n+1 are counted (``sync-late-writes``).
        Raises MessageError (no such bus here, no SYNC cycle, ``n`` long past), ReadTimeout
        after ``timeout`` seconds. See :mod:`chcos.user.cycles`."""
        return wait_cycle(self._t, self._k, getattr(self._mm.devices, "drivers", ()), bus, n,
                          timeout)

    @types.coroutine
    def checkpoint(self) -> Generator[Any, Any, None]:
        """Give the processor to any ready task of higher or equal priority, then go on."""
        yield YIELD

    @property
    def commander(self) -> str | None:
        """The name of the task that owns (commands) this one now; None if idle or owned by the
        host (world-model context, ``chcos.user.worldmodel.context``)."""
        owner = self._t.owner
        if owner is None or owner.src not in self._mm.tsktab:
            return None
        return owner.src

    @property
    def state_dir(self) -> Path:
        """Where this system keeps run state beside its map (learned world-model data goes to
        ``state_dir/learned``): the directory of its sysfile.map (the satellite's state
        directory, ``chcos run``'s work directory), else its base directory."""
        return Path(self._mm.state_dir)

    # ---- devices with a profile ---------------------------------------------------------------
    def axis(self, name: str) -> AxisHandle:
        """The CiA 402 axis ``name`` (a device-map table with ``profile = "cia402"``) on one of
        this task's output ports: commands that complete (``await ctx.axis("x").enable()``) and
        its readings (:mod:`chcos.user.axes`). Raises MessageError if it is not on an output
        port or not an axis driven by this process."""
        return axis_handle(self._t, self._k, self._mm.devices, name)

    # ---- world model queries ----------------------------------------------------------------
    @types.coroutine
    def ask(self, peer: str, topic: str, *args: Any,
            timeout: float | None = None) -> Generator[Any, Any, Any]:
        """Ask task ``peer``'s world model about ``topic`` (a request on a link joining the two
        tasks, answered by the peer's model, never by reading its memory). A peer on another
        satellite is asked over the link: this task waits for the answer, at most ``timeout``
        seconds if given. Raises MessageError if no link joins the tasks, the peer has no model,
        the model has no answer, or the peer's satellite is down or dies before answering;
        ReadTimeout if no answer came within ``timeout``."""
        me = self._t.name
        mm = self._mm
        mt = mm.msgtab
        joining = next((lk for a, b in ((me, peer), (peer, me)) for ty in LinkType
                        if (lk := mt.get(a, b, ty)) is not None), None)
        if joining is None:
            raise MessageError(f"task {me} has no link to {peer}: it may not query its world model")
        target = mm.tsktab.get(peer)
        if mm.is_local(target.machine):
            answer = mm.world_answer(target, topic, args)
            yield YIELD
            return answer
        t = self._t
        mm.ask_remote(t, joining, target, topic, args)
        self._k.block(t, TaskState.WAITING)
        self._arm_timeout(timeout, f"the answer of {peer} about {topic!r}")
        return (yield BLOCK)
