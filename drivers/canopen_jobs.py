"""canopen_jobs - the typed jobs of the ``canopen`` driver's I/O thread (beside the shared
``poll`` and ``write`` jobs of :mod:`drivers.jobs`): a node's boot procedure, the report of a
node held in PRE-OPERATIONAL, a restart of the recovery policy, the probe of an actuator whose
write failed, and the work of the
CiA 402 axes it hosts (readings, commands, the node's loss, a cycle of their engines). Each
travels as the ``what`` of a :class:`drivers.jobs.Job` with op ``JobOp.OWN`` (the axes' cycle
also as a paced ``JobOp.POLL`` key) and is dispatched with ``match``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class AxisCycle:
    """One cycle of the hosted axes' engines (timeouts, the fault reset's edge, resends): the
    key of their paced poll, or a job of its own while a flush waits for a running command."""


@dataclass(frozen=True)
class BootNode:
    """Run the boot procedure of node ``node`` for boot ``generation`` (stale if the node
    booted again meanwhile)."""

    node: int
    generation: int


@dataclass(frozen=True)
class ReportHeld:
    """Node ``node`` stays PRE-OPERATIONAL (or STOPPED) after its NMT start: read its error
    register and report it with the last EMCY."""

    node: int
    generation: int


@dataclass(frozen=True)
class RestartNode:
    """Node ``node`` left OPERATIONAL and its recovery step ``episode`` is due: if its cause
    cleared (error register 0x1001 reads 0), send the next restart of its policy (stale if
    anything happened to the node meanwhile: a newer step, a boot-up, the host's command)."""

    node: int
    episode: int


@dataclass(frozen=True)
class Probe:
    """An SDO exchange with the node of actuator ``device`` whose write failed: its answer
    clears the failure (no latch, issue 38)."""

    device: str


@dataclass(frozen=True)
class AxisFeed:
    """Values of axis ``device``'s objects from one TPDO (engine object -> raw value), and
    its receive mark (:meth:`drivers.canopen_axis.AxisHost.pdo_received`; None: unmarked)."""

    device: str
    values: tuple[tuple[Any, int], ...]
    received: int | None = None


@dataclass(frozen=True)
class AxisCommand:
    """Start a command of axis ``device`` (a :class:`drivers.canopen_axis.AxisCall`); ``done``
    gets its result or the exception that refused it."""

    device: str
    call: Any
    done: Callable[[Any], None] | None


@dataclass(frozen=True)
class AxisLost:
    """The node of axis ``device`` failed or rebooted: the engine forgets the drive, and the
    safe stop starts (it completes when the drive is heard again)."""

    device: str
    reason: str


@dataclass(frozen=True)
class AxisRefresh:
    """The node of axis ``device`` is ready: read the axis's objects by SDO, so its sensors
    show the drive before any command or TPDO."""

    device: str


CanopenJob = (BootNode | ReportHeld | RestartNode | Probe | AxisFeed | AxisCommand | AxisLost
              | AxisRefresh | AxisCycle)
