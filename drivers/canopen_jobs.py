"""canopen_jobs - the typed jobs of the ``canopen`` driver's I/O thread (beside the shared
``poll`` and ``write`` jobs of :mod:`drivers.jobs`): a node's boot procedure, the report of a
node held in PRE-OPERATIONAL, the probe of an actuator whose write failed. Each travels as the
``what`` of a :class:`drivers.jobs.Job` with op :data:`OP` and is dispatched with ``match``.
"""

from __future__ import annotations

from dataclasses import dataclass

#: the op of every job defined here
OP = "canopen"


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
class Probe:
    """An SDO exchange with the node of actuator ``device`` whose write failed: its answer
    clears the failure (no latch, issue 38)."""

    device: str


CanopenJob = BootNode | ReportHeld | Probe
