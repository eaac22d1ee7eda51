"""emergency_system - the system the emergency benchmark (:mod:`chcos.apps.bench.emergency`) runs.

Four background sensors ``B0..B3`` read by four level-1 driver tasks ``D0..D3`` (:func:`drive`)
that command ``M0..M3``; the light curtain ``LC`` (interrupt priority 99) read by the guard ``G``
(:func:`guard`); the exception task ``X`` (:func:`watch`) that invokes the assassin ``K``
(:func:`assassin`) on the priority-99 link X/K; all on one python-can virtual bus
(:func:`devmap`), built by :func:`build`. Errors: BusError if the bus cannot be opened,
InstallError if an install fails.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from chcos.apps.fig65.common import FAN_IN
from chcos.devices.spec import BusSpec, DeviceMap, DeviceSpec
from chcos.kernel.clock import Clock, RealClock
from chcos.system.embedded import System
from chcos.user.context import TaskContext

__all__ = ["ACTUATORS", "BACKGROUND", "LC_ID", "assassin", "build", "devmap", "drive", "guard",
           "watch"]

BACKGROUND = ("B0", "B1", "B2", "B3")
ACTUATORS = ("M0", "M1", "M2", "M3")
LC_ID = 0x050
_M = "chcos.apps.bench.emergency_system"


# --------------------------------------------------------------------------- tasks


async def drive(ctx: TaskContext, command: Any) -> None:
    """D0..D3: read the background sensor; every fifth reading command the actuator (never
    with its safe value 0) and report the reading upward."""
    read, write, put = ctx.read, ctx.write, ctx.put
    n = 0
    while True:
        v = await read(0)
        n += 1
        if n % FAN_IN == 0:
            write(0, (v % 1000) + 1)
            put(v)


async def guard(ctx: TaskContext, command: Any) -> None:
    """G: report every light-curtain reading upward: ``("intruder", v)`` for v != 0."""
    read, put = ctx.read, ctx.put
    while True:
        v = await read(0)
        put(("intruder", v) if v else ("clear", v))


async def watch(ctx: TaskContext, command: Any) -> None:
    """X, the exception task: on an intruder report from any lower task, invoke the assassin
    at once (without waiting for it)."""
    while True:
        _src, value = await ctx.read_exception()
        if isinstance(value, tuple) and value[0] == "intruder":
            await ctx.invoke("K", value, wait=False)


async def assassin(ctx: TaskContext, command: Any) -> int:
    """K, the assassin: e-stop (every actuator to its safe value), then suspend the tasks named
    in its ``victims`` parameter, as the welding cell's assassin does: the safe values go out
    first, and no victim can run in between (K's step is not interrupted). Completes with how
    many actuators were written."""
    written = ctx.estop(f"intruder {command!r}")
    for name in str(ctx.params.get("victims", "")).split(","):
        if name:
            ctx.suspend_task(name)
    return written


# --------------------------------------------------------------------------- the system


def devmap(channel: str) -> DeviceMap:
    """The devices on one python-can virtual bus ``channel`` (raw 32-bit signals)."""
    bus = BusSpec("can0", "can", {"interface": "virtual", "channel": channel, "poll": 0.05})

    def addr(cid: int) -> dict[str, Any]:
        return {"id": cid, "start": 0, "length": 32, "dlc": 4}

    devs = [DeviceSpec(b, "sensor", 0, "can0", addr(0x100 + i)) for i, b in enumerate(BACKGROUND)]
    devs.append(DeviceSpec("LC", "sensor", 0, "can0", addr(LC_ID), priority=99))
    devs += [DeviceSpec(a, "actuator", 0, "can0", addr(0x200 + i), limits=(0.0, 4.0e9),
                        safe_value=0.0) for i, a in enumerate(ACTUATORS)]
    return DeviceMap((bus,), tuple(devs))


def build(channel: str, *, devices: DeviceMap | None = None, clock: Clock | None = None
          ) -> System:
    """The system, installed and every task invoked (not started): on the virtual CAN
    ``channel`` and real time, or on ``devices`` (same device names) and ``clock`` (tests use
    memory devices on virtual time). Raises BusError if the bus cannot be opened, InstallError
    if an install fails."""
    s = System(devices if devices is not None else devmap(channel),
               clock=clock if clock is not None else RealClock(), machines=[0],
               base_dir=Path.cwd())
    for i, (b, a) in enumerate(zip(BACKGROUND, ACTUATORS, strict=True)):
        s.execute(f"install -m0i1o1 --code={_M}:drive D{i} {b} {a}")
    s.execute(f"install -m0i1 --code={_M}:guard G LC")
    victims = ",".join(f"D{i}" for i in range(len(BACKGROUND)))
    s.execute(f"install -m0 --role=assassin --level=2 --param=victims={victims} "
              f"--code={_M}:assassin K")
    s.execute(f"install -m0o1 --role=exception --level=3 --code={_M}:watch X K")
    s.execute("setpri -99 X K")
    for t in ("X", "G", *(f"D{i}" for i in range(len(BACKGROUND)))):
        s.invoke(t)
    return s
