"""canopen_lifecycle - the life of one remote CANopen node as the ``canopen`` driver sees it: a
state machine (:class:`NodeLifecycle`) fed by boot-up messages, the NMT state in each heartbeat,
the outcome of the driver's boot procedure (identity check, configuration download, NMT start),
the node's recovery policy (:class:`RestartPolicy`: a node that leaves OPERATIONAL by itself is
started again once its cause clears, with a backoff and a limit) and the host's NMT commands, and
the status the driver publishes for it (:class:`NodeStatus`). Pure: no bus I/O, no threads, no
clock of its own (times are given by the owner, on the host's clock); the owner serialises calls
(see :class:`drivers.canopen_remote.ManagedNode`).

The states, in the order a healthy boot goes through them::

    WAITING_BOOT -> IDENTITY_CHECKED -> CONFIGURED -> STARTED -> OPERATIONAL
                                                  \\-> PREOP_HELD   (started, stays PRE-OPERATIONAL)
    OPERATIONAL -> LEFT_OPERATIONAL (its heartbeat says PRE-OPERATIONAL or STOPPED)
                -> STARTED (a restart, once the cause cleared) -> OPERATIONAL
                -> PREOP_HELD (the restarts of the policy used up: it refuses)
    any state -> HOST_HELD (the host's ``nmt stop``/``nmt preop``; ``nmt start`` ends it)
    any state -> FAILED (identity mismatch, configuration refused)
    any state -> WAITING_BOOT (a boot-up message: the node rebooted)

A node whose map entry says ``nmt_start = false`` is not started by the driver: CONFIGURED is
its ready state (it may be PRE-OPERATIONAL or OPERATIONAL, as whoever manages it decides), and it
is never restarted.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum, IntEnum

#: non-OPERATIONAL heartbeats after an NMT start that make it a start not taken (the first may
#: have been sent before the start command arrived)
HELD_AFTER = 2
#: the longest wait before a restart (s), however many came before (the backoff doubles)
MAX_BACKOFF = 30.0
#: seconds of OPERATIONAL after which a node's restarts count from 0 again (a node that left
#: OPERATIONAL once an hour is not one restart nearer its limit each time)
RESTART_STABLE = 10.0
#: the restart policy's defaults (node keys ``restart_limit``, ``restart_backoff``)
DEFAULT_RESTART_LIMIT = 5
DEFAULT_RESTART_BACKOFF = 1.0


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

    @property
    def text(self) -> str:
        """The state as CiA 301 spells it (``PRE-OPERATIONAL``)."""
        return self.name.replace("_", "-")


class NmtCommand(IntEnum):
    """The NMT module control commands (CiA 301 7.2.8.3.1): the command specifier."""

    START = 0x01
    STOP = 0x02
    PREOP = 0x80
    RESET = 0x81
    RESET_COMM = 0x82

    @property
    def word(self) -> str:
        """The host command's word (``nmt reset-comm 5``)."""
        return self.name.lower().replace("_", "-")

    @classmethod
    def of_word(cls, word: str) -> NmtCommand:
        """The command for host word ``word``; raises ValueError naming the words."""
        for c in cls:
            if c.word == word:
                return c
        raise ValueError(f"no NMT command {word!r}; expected one of "
                         f"{', '.join(c.word for c in cls)}")


class NodeLifecycle(Enum):
    """Where a node is in its life (see the module doc)."""

    WAITING_BOOT = "waiting for boot-up"
    IDENTITY_CHECKED = "identity checked"
    CONFIGURED = "configured"
    STARTED = "NMT start sent"
    OPERATIONAL = "operational"
    LEFT_OPERATIONAL = "left OPERATIONAL"
    PREOP_HELD = "held in PRE-OPERATIONAL"
    HOST_HELD = "held by the host"
    FAILED = "failed"


@dataclass(frozen=True)
class RestartPolicy:
    """What the driver does with a node that leaves OPERATIONAL by itself: start it again once
    its cause cleared (its error register 0x1001 reads 0, an error-reset EMCY, its heartbeat
    back after a loss), at most ``limit`` times (0: never), restart n waiting ``backoff`` *
    2**(n-1) seconds (at most :data:`MAX_BACKOFF`) after the node left or the previous restart
    was not taken."""

    limit: int = DEFAULT_RESTART_LIMIT
    backoff: float = DEFAULT_RESTART_BACKOFF

    def delay(self, n: int) -> float:
        """Seconds before restart ``n`` (1-based)."""
        return min(self.backoff * 2.0 ** max(0, n - 1), MAX_BACKOFF)


@dataclass(frozen=True)
class NodeStatus:
    """What the driver knows of one node, for ``chcos map``, ``monitor`` and metrics.

    ``lifecycle`` the state; ``ready`` whether the node is in the state the map requires and its
    heartbeat is not lost (its devices may be OK); ``confirmed`` whether a heartbeat confirmed
    that state (False for a node without heartbeat, whose OPERATIONAL is assumed after the NMT
    start); ``nmt`` the NMT state of its last heartbeat (None before any); ``boots`` boot-up
    messages seen; ``nmt_starts`` NMT start commands sent (restarts and the host's included);
    ``heartbeat_losses`` times its heartbeat was declared lost (a loss that lasts counts once,
    each new one after its heartbeat came back once more); ``emcys`` EMCY messages received;
    ``stores`` configurations stored in the node (``store_config``: 0x1010 answered);
    ``error_register`` 0x1001 as last read (None if never read); ``last_emcy`` the text of the
    last EMCY; ``reason`` why it is not ready ("" when it is); ``restarts`` restarts the
    recovery policy sent since the node last booted; ``heartbeat_lost`` whether its heartbeat
    is lost now."""

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
    restarts: int = 0
    heartbeat_lost: bool = False


class Lifecycle:
    """The state machine of one node (see the module doc). Every method raises nothing; the
    owner reads :attr:`state` and :meth:`ready` after each event. ``now`` arguments are the
    host clock's time (reasons name it)."""

    def __init__(self, node: int, nmt_start: bool, supervised: bool,
                 policy: RestartPolicy | None = None) -> None:
        self.node = node
        #: whether the driver sends the NMT start (the map's ``nmt_start``)
        self.nmt_start = nmt_start
        #: whether the node has heartbeat supervision (then OPERATIONAL needs its confirmation)
        self.supervised = supervised
        self.policy = policy or RestartPolicy()
        self.state = NodeLifecycle.WAITING_BOOT
        self.nmt: NmtState | None = None
        self.confirmed = False
        self.boots = 0
        self.nmt_starts = 0
        #: heartbeat losses declared (see :meth:`heartbeat_lost`) and EMCYs received
        self.heartbeat_losses = 0
        self.emcys = 0
        #: whether the node's heartbeat is lost now (:meth:`heartbeat_lost`, :meth:`heartbeat`)
        self.lost = False
        #: configurations stored in the node (0x1010 "save" answered)
        self.stores = 0
        #: the boot the current procedure belongs to (a reboot meanwhile makes it stale)
        self.generation = 0
        #: the recovery step a queued restart belongs to (a newer event makes it stale)
        self.episode = 0
        self.error_register: int | None = None
        #: non-OPERATIONAL heartbeats since the last NMT start (one may have been on its way)
        self.not_started_beats = 0
        self.last_emcy = ""
        self.reason = "no boot-up or answer seen yet"
        #: restarts sent in this recovery (back to 0 after :data:`RESTART_STABLE` s running,
        #: at a boot and at the host's ``nmt start``), and in all since the last boot
        self.restarts = 0
        self.restarts_total = 0
        #: when the node last left OPERATIONAL by itself and what its heartbeat said then
        self.left_at: float | None = None
        self.left_nmt: NmtState | None = None
        #: when it last became OPERATIONAL (host clock)
        self.operational_since: float | None = None
        #: whether the NMT start in flight is a restart of the policy (not the boot's start)
        self.restarting = False
        #: True from the host's ``nmt reset``/``reset-comm`` until the boot-up it causes
        self.host_reset = False

    def ready(self) -> bool:
        """True while the node is in the state the map requires."""
        if self.nmt_start:
            return self.state is NodeLifecycle.OPERATIONAL
        return self.state is NodeLifecycle.CONFIGURED and self.nmt in (
            None, NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL)

    def booted(self) -> int:
        """A boot-up message arrived: a new life begins; returns its generation."""
        self.boots += 1
        why = ("rebooted by the host's nmt reset (boot-up message)" if self.host_reset
               else "booted (boot-up message)")
        self.host_reset = False
        self.restarts = self.restarts_total = 0
        self.left_at = None
        return self.restart(why)

    def restart(self, reason: str) -> int:
        """Begin the boot procedure again (driver start, or a boot-up); its generation."""
        self.generation += 1
        self.episode += 1
        self.state = NodeLifecycle.WAITING_BOOT
        self.confirmed = False
        self.restarting = False
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

    def started(self, now: float = 0.0) -> None:
        """The NMT start of this boot went out (once per boot; the host's ``nmt start`` too).
        Without heartbeat supervision there is nothing to confirm it: OPERATIONAL is
        assumed."""
        self.nmt_starts += 1
        self.not_started_beats = 0
        self.episode += 1
        if self.supervised:
            self.state = NodeLifecycle.STARTED
            self.reason = "NMT start sent, waiting for an OPERATIONAL heartbeat"
        else:
            self._operational(now)

    def _operational(self, now: float) -> None:
        self.state = NodeLifecycle.OPERATIONAL
        self.reason = ""
        self.restarting = False
        self.operational_since = now

    # -- the recovery policy ------------------------------------------------------------------

    def _left_text(self) -> str:
        at = "" if self.left_at is None else f" at t={self.left_at:.1f} s"
        said = "" if self.left_nmt is None else f" (heartbeat says {self.left_nmt.text})"
        return f"left OPERATIONAL{at}{said}"

    def next_restart(self) -> tuple[int, float] | None:
        """The number of the next restart and its delay, None when the policy is used up."""
        n = self.restarts + 1
        if n > self.policy.limit:
            return None
        return n, self.policy.delay(n)

    def recovery_reason(self, waiting: str = "") -> str:
        """Why the node is not ready while it recovers: when it left and what it said, the
        next restart (or that there is none), and ``waiting`` (what that restart waits for)."""
        nxt = self.next_restart()
        if self.policy.limit == 0:
            plan = "not restarted (restart_limit = 0)"
        elif nxt is None:
            plan = f"{self.policy.limit} restart(s) of {self.policy.limit} did not keep it " \
                   f"OPERATIONAL: it refuses"
        else:
            plan = f"restart {nxt[0]} of {self.policy.limit} in {nxt[1]:.1f} s"
        return f"{self._left_text()}; {plan}" + (f"; {waiting}" if waiting else "")

    def left(self, nmt: NmtState, now: float) -> None:
        """The node's heartbeat says ``nmt`` (not OPERATIONAL) although it ran: it left
        OPERATIONAL by itself. Its restarts count from 0 again if it ran for
        :data:`RESTART_STABLE` s."""
        since = self.operational_since
        if since is not None and now - since >= RESTART_STABLE:
            self.restarts = 0
        self.left_at, self.left_nmt = now, nmt
        self.confirmed = False
        self.restarting = False
        self.episode += 1
        if self.next_restart() is None:
            self.state = NodeLifecycle.PREOP_HELD
        else:
            self.state = NodeLifecycle.LEFT_OPERATIONAL
        self.reason = self.recovery_reason()

    def waiting_for_cause(self, why: str) -> None:
        """The next restart waits: the cause did not clear yet (``why`` says what it waits
        for); a new episode (the check is made again later)."""
        self.episode += 1
        self.reason = self.recovery_reason(why)

    def restarted(self, now: float = 0.0) -> None:
        """A restart of the policy went out at host time ``now`` (the cause cleared): counted,
        and confirmed as any start is."""
        self.restarts += 1
        self.restarts_total += 1
        self.started(now)
        if self.state is NodeLifecycle.STARTED:     # to be confirmed by its heartbeat
            self.restarting = True
            self.reason = (f"{self._left_text()}; restart {self.restarts} of "
                           f"{self.policy.limit} sent, waiting for an OPERATIONAL heartbeat")

    def cause_cleared(self) -> bool:
        """An error-reset EMCY (or the heartbeat back): True if the node waits for a restart
        (left OPERATIONAL, or refused its last start) and so should be tried now; a refusing
        node's restarts count from 0 again (the cause it refused for is gone)."""
        if self.state is NodeLifecycle.PREOP_HELD and self.nmt_start:
            self.restarts = 0
            if self.left_at is None:
                self.left_nmt = self.nmt
            self.state = NodeLifecycle.LEFT_OPERATIONAL
            self.episode += 1
            self.reason = self.recovery_reason()
            return self.policy.limit > 0
        return self.state is NodeLifecycle.LEFT_OPERATIONAL

    # -- the host's commands ------------------------------------------------------------------

    def host_command(self, command: NmtCommand, now: float) -> None:
        """The host sent ``command`` to the node: ``start`` ends a hold and the recovery
        (restarts count from 0), ``stop``/``preop`` hold a started node there (no restart by
        the policy), ``reset``/``reset-comm`` make its boot-up the host's."""
        self.episode += 1
        match command:
            case NmtCommand.START if self.state is NodeLifecycle.OPERATIONAL:
                self.nmt_starts += 1        # running already: nothing changes
            case NmtCommand.START:
                self.restarts = 0
                self.left_at = None
                if self.state not in (NodeLifecycle.FAILED, NodeLifecycle.WAITING_BOOT,
                                      NodeLifecycle.IDENTITY_CHECKED):
                    self.started(now)
                    if self.supervised:
                        self.reason = "the host's nmt start sent, waiting for an OPERATIONAL " \
                                      "heartbeat"
                else:
                    self.nmt_starts += 1
            case NmtCommand.STOP | NmtCommand.PREOP if self.nmt_start and self.state not in (
                    NodeLifecycle.FAILED, NodeLifecycle.WAITING_BOOT,
                    NodeLifecycle.IDENTITY_CHECKED):
                self.state = NodeLifecycle.HOST_HELD
                self.confirmed = False
                self.restarting = False
                self.reason = f"held by the host (nmt {command.word} at t={now:.1f} s); " \
                              f"nmt start ends it"
            case NmtCommand.RESET | NmtCommand.RESET_COMM:
                self.host_reset = True
            case _:
                pass

    # -- heartbeats and EMCY ------------------------------------------------------------------

    def heartbeat(self, nmt: NmtState, now: float = 0.0) -> None:
        """A heartbeat (not a boot-up) with state ``nmt`` at host time ``now``."""
        self.nmt = nmt
        self.lost = False
        if nmt is NmtState.OPERATIONAL:
            if self.state in (NodeLifecycle.STARTED, NodeLifecycle.PREOP_HELD,
                              NodeLifecycle.LEFT_OPERATIONAL, NodeLifecycle.OPERATIONAL):
                if self.state is not NodeLifecycle.OPERATIONAL:
                    self._operational(now)
                self.confirmed = True
            return
        if self.state is NodeLifecycle.OPERATIONAL and self.confirmed:
            self.left(nmt, now)             # it ran, and left by itself
            return
        if self.state not in (NodeLifecycle.STARTED, NodeLifecycle.OPERATIONAL):
            return
        # no OPERATIONAL heartbeat since the start yet: the first may have left the node
        # before the NMT start reached it
        self.not_started_beats += 1
        if self.not_started_beats < HELD_AFTER:
            return
        self.confirmed = False
        if self.restarting:                 # a restart of the policy not taken
            self.restarting = False
            self.left_nmt = nmt
            self.episode += 1
            self.state = (NodeLifecycle.PREOP_HELD if self.next_restart() is None
                          else NodeLifecycle.LEFT_OPERATIONAL)
            self.reason = self.recovery_reason(f"restart {self.restarts} not taken")
            return
        self.state = NodeLifecycle.PREOP_HELD
        self.reason = f"stays {nmt.text} after the NMT start"

    def heartbeat_lost(self) -> None:
        """The node's heartbeat was declared lost (once per loss: the owner calls it when
        its supervision goes from alive to lost)."""
        self.heartbeat_losses += 1
        self.lost = True

    def emcy(self, text: str) -> None:
        """An EMCY arrived (``text`` describes it)."""
        self.emcys += 1
        self.last_emcy = text

    def status(self, lost_reason: str = "") -> NodeStatus:
        """The published status; ``lost_reason`` says why the heartbeat is lost (while it is:
        then the node is not ready whatever its state)."""
        ready = self.ready() and not self.lost
        reason = "" if ready else (self.reason if not self.lost or not self.ready()
                                   else lost_reason or "heartbeat lost")
        return NodeStatus(self.node, self.state, ready, self.confirmed, self.nmt,
                          self.boots, self.nmt_starts, self.error_register, self.last_emcy,
                          reason, self.heartbeat_losses, self.emcys, self.stores,
                          self.restarts_total, self.lost)
