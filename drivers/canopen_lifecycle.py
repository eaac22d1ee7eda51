"""canopen_lifecycle - the life of one remote CANopen node as the ``canopen`` driver sees it: a
state machine (:class:`NodeLifecycle`) fed by boot-up messages, the NMT state in each heartbeat and
the outcome of the driver's boot procedure (identity check, configuration download, NMT start),
and the status the driver publishes for it (:class:`NodeStatus`). Pure: no bus I/O, no threads of
its own (the owner serialises calls, see :class:`drivers.canopen_remote.ManagedNode`).

The states, in the order a healthy boot goes through them::

    WAITING_BOOT -> IDENTITY_CHECKED -> CONFIGURED -> STARTED -> OPERATIONAL
                                                  \\-> PREOP_HELD   (started, stays PRE-OPERATIONAL)
    any state -> FAILED (identity mismatch, configuration refused)
    any state -> WAITING_BOOT (a boot-up message: the node rebooted)

A node whose map entry says ``nmt_start = false`` is not started by the driver: CONFIGURED is
its ready state (it may be PRE-OPERATIONAL or OPERATIONAL, as whoever manages it decides).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum, IntEnum

#: non-OPERATIONAL heartbeats after the NMT start that make a node "held" (the first may have
#: been sent before the start command arrived)
HELD_AFTER = 2


class NmtState(IntEnum):
    """The NMT state a node reports in its heartbeat (CiA 301 7.2.8.3.2.2): 0 is the boot-up."""

    BOOT_UP = 0
    STOPPED = 4
    OPERATIONAL = 5
    PRE_OPERATIONAL = 127

    @classmethod
    def of(cls, code: int) -> NmtState | None:
        """The state for heartbeat byte ``code`` (toggle bit ignored), None if it is none."""
        try:
            return cls(code & 0x7F)
        except ValueError:
            return None


class NodeLifecycle(Enum):
    """Where a node is in its life (see the module doc)."""

    WAITING_BOOT = "waiting for boot-up"
    IDENTITY_CHECKED = "identity checked"
    CONFIGURED = "configured"
    STARTED = "NMT start sent"
    OPERATIONAL = "operational"
    PREOP_HELD = "held in PRE-OPERATIONAL"
    FAILED = "failed"


@dataclass(frozen=True)
class NodeStatus:
    """What the driver knows of one node, for ``chcos map``, ``monitor`` and metrics.

    ``lifecycle`` the state; ``ready`` whether the node is in the state the map requires (its
    devices may be OK); ``confirmed`` whether a heartbeat confirmed that state (False for a node
    without heartbeat, whose OPERATIONAL is assumed after the NMT start); ``nmt`` the NMT state of
    its last heartbeat (None before any); ``boots`` boot-up messages seen; ``nmt_starts`` NMT start
    commands sent; ``heartbeat_losses`` times its heartbeat was declared lost (a loss that lasts
    counts once, each new one after its heartbeat came back once more); ``emcys`` EMCY messages
    received; ``stores`` configurations stored in the node (``store_config``: 0x1010
    answered); ``error_register`` 0x1001 as last read (None if never read); ``last_emcy`` the
    text of the last EMCY; ``reason`` why it is not ready ("" when it is)."""

    node: int
    lifecycle: NodeLifecycle
    ready: bool
    confirmed: bool
    nmt: NmtState | None
    boots: int
    nmt_starts: int
    error_register: int | None
    last_emcy: str
    reason: str
    heartbeat_losses: int = 0
    emcys: int = 0
    stores: int = 0


class Lifecycle:
    """The state machine of one node (see the module doc). Every method returns nothing and
    raises nothing; the owner reads :attr:`state` and :meth:`ready` after each event."""

    def __init__(self, node: int, nmt_start: bool, supervised: bool) -> None:
        self.node = node
        #: whether the driver sends the NMT start (the map's ``nmt_start``)
        self.nmt_start = nmt_start
        #: whether the node has heartbeat supervision (then OPERATIONAL needs its confirmation)
        self.supervised = supervised
        self.state = NodeLifecycle.WAITING_BOOT
        self.nmt: NmtState | None = None
        self.confirmed = False
        self.boots = 0
        self.nmt_starts = 0
        #: heartbeat losses declared (see :meth:`heartbeat_lost`) and EMCYs received
        self.heartbeat_losses = 0
        self.emcys = 0
        #: configurations stored in the node (0x1010 "save" answered)
        self.stores = 0
        #: the boot the current procedure belongs to (a reboot meanwhile makes it stale)
        self.generation = 0
        self.error_register: int | None = None
        #: non-OPERATIONAL heartbeats since the NMT start (one may have been on its way)
        self.not_started_beats = 0
        self.last_emcy = ""
        self.reason = "no boot-up or answer seen yet"

    def ready(self) -> bool:
        """True while the node is in the state the map requires."""
        if self.nmt_start:
            return self.state is NodeLifecycle.OPERATIONAL
        return self.state is NodeLifecycle.CONFIGURED and self.nmt in (
            None, NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL)

    def booted(self) -> int:
        """A boot-up message arrived: a new life begins; returns its generation."""
        self.boots += 1
        return self.restart("booted (boot-up message)")

    def restart(self, reason: str) -> int:
        """Begin the boot procedure again (driver start, or a boot-up); its generation."""
        self.generation += 1
        self.state = NodeLifecycle.WAITING_BOOT
        self.confirmed = False
        self.reason = reason
        return self.generation

    def no_answer(self, reason: str) -> None:
        """The boot procedure found the node silent: wait for its boot-up."""
        self.state = NodeLifecycle.WAITING_BOOT
        self.reason = reason

    def identity_checked(self) -> None:
        self.state = NodeLifecycle.IDENTITY_CHECKED

    def configured(self) -> None:
        self.state = NodeLifecycle.CONFIGURED
        self.reason = "" if not self.nmt_start else "configured, not started yet"

    def failed(self, reason: str) -> None:
        """Identity mismatch or configuration refused: stays so until the next boot-up."""
        self.state = NodeLifecycle.FAILED
        self.reason = reason

    def started(self) -> None:
        """The NMT start went out (once per boot). Without heartbeat supervision there is
        nothing to confirm it: OPERATIONAL is assumed."""
        self.nmt_starts += 1
        self.not_started_beats = 0
        if self.supervised:
            self.state = NodeLifecycle.STARTED
            self.reason = "NMT start sent, waiting for an OPERATIONAL heartbeat"
        else:
            self.state = NodeLifecycle.OPERATIONAL
            self.reason = ""

    def heartbeat(self, nmt: NmtState) -> None:
        """A heartbeat (not a boot-up) with state ``nmt``."""
        self.nmt = nmt
        if nmt is NmtState.OPERATIONAL:
            if self.state in (NodeLifecycle.STARTED, NodeLifecycle.PREOP_HELD,
                              NodeLifecycle.OPERATIONAL):
                self.state = NodeLifecycle.OPERATIONAL
                self.confirmed = True
                self.reason = ""
            return
        if (self.state in (NodeLifecycle.STARTED, NodeLifecycle.OPERATIONAL)
                and not self.confirmed):
            # no OPERATIONAL heartbeat since the start yet: the first may have left the node
            # before the NMT start reached it
            self.not_started_beats += 1
            if self.not_started_beats < HELD_AFTER:
                return
        if self.state in (NodeLifecycle.STARTED, NodeLifecycle.OPERATIONAL):
            self.state = NodeLifecycle.PREOP_HELD
            self.confirmed = False
            self.reason = f"stays {nmt.name.replace('_', '-')} after the NMT start"

    def heartbeat_lost(self) -> None:
        """The node's heartbeat was declared lost (once per loss: the owner calls it when
        its supervision goes from alive to lost)."""
        self.heartbeat_losses += 1

    def emcy(self, text: str) -> None:
        """An EMCY arrived (``text`` describes it)."""
        self.emcys += 1
        self.last_emcy = text

    def status(self) -> NodeStatus:
        """The published status."""
        return NodeStatus(self.node, self.state, self.ready(), self.confirmed, self.nmt,
                          self.boots, self.nmt_starts, self.error_register, self.last_emcy,
                          "" if self.ready() else self.reason, self.heartbeat_losses,
                          self.emcys, self.stores)
