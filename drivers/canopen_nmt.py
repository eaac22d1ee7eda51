"""canopen_nmt - what the ``canopen`` driver sends as its nodes' NMT master by its own decision
or the host's: the restarts of a node's recovery policy (:class:`drivers.canopen_lifecycle.
RestartPolicy`: a node that left OPERATIONAL gets an NMT start once its cause cleared, its error
register read first) and the host's ``nmt start|stop|preop|reset|reset-comm NODE``. The boot's
own NMT start is part of the boot procedure (:meth:`drivers.canopen_node.CanopenDriver._boot`).
:class:`NmtMaster` is composed by the driver with its :class:`drivers.canopen_events.NodeEvents`
(the nodes, their devices' health, the host).
"""

from __future__ import annotations

import can
from canopen.sdo.exceptions import SdoCommunicationError

from chcos.errors import BusError
from drivers.canopen_events import NodeEvents
from drivers.canopen_jobs import RestartNode
from drivers.canopen_lifecycle import NmtCommand, NodeLifecycle


class NmtMaster:
    """The restarts and the host's NMT commands of one bus's nodes (see the module doc)."""

    def __init__(self, events: NodeEvents) -> None:
        self._events = events

    def restart(self, job: RestartNode) -> None:
        """A restart of node ``job.node``'s recovery policy is due (I/O thread): its error
        register is read; clear (0, no 0x1001, or a node hosting axes, whose drive's fault is
        its axes' to reset) it gets the NMT start, else the restart waits and the register is
        read again after the same backoff. Stale (nothing done) if anything happened to the
        node meanwhile. Raises ``can.CanError`` if the start cannot be sent."""
        ev = self._events
        node = ev.nodes[job.node]

        def due() -> bool:
            lc = node.lifecycle
            return job.episode == lc.episode and lc.state is NodeLifecycle.LEFT_OPERATIONAL
        with node.lock:
            if not due():
                return
        reg: int | None = None
        waiting = ""
        if not node.axes:
            try:
                reg = node.read_error_register()
            except SdoCommunicationError as exc:
                waiting = f"no SDO answer to the read of 0x1001 ({exc}): asked again"
            if reg:
                waiting = (f"error register 0x1001 = 0x{reg:02X}: the restart waits for it "
                           f"to read 0 or for an error-reset EMCY")
        with node.lock:
            if not due():
                return
            lc = node.lifecycle
            if reg is not None:
                lc.error_register = reg
            if waiting:
                lc.waiting_for_cause(waiting)
            else:
                lc.restarted(ev.host.now())
        if waiting:
            ev.restate(node)
            ev.arm_restart(node)
            return
        node.send_nmt_start()
        ev.host.stat(ev.bus, "nmt-restarts")
        ev.judge(node, "restarted")
        ev.restate(node)

    def command(self, command: NmtCommand | str, node: int, running: bool) -> str:
        """Send NMT ``command`` (or its host word) to node ``node`` now, from the calling
        thread (an NMT command is unconfirmed: the node's heartbeat tells what it did). The
        node's lifecycle takes it: ``start`` ends a hold and the recovery, ``stop``/``preop``
        hold a started node there (its devices fail, the recovery policy leaves it alone),
        ``reset``/``reset-comm`` make the boot-up that follows the host's (not a bus error;
        the boot procedure runs as for any boot-up). Returns the answer naming the node and
        the state it was in. Raises BusError for a node not on the bus, a driver not
        ``running``, a command that is none, or a frame that cannot be sent."""
        ev = self._events
        try:
            cmd = command if isinstance(command, NmtCommand) else NmtCommand.of_word(command)
        except ValueError as exc:
            raise BusError(f"canopen bus {ev.bus}: nmt: {exc}") from None
        managed = ev.nodes.get(node)
        if managed is None:
            raise BusError(f"canopen bus {ev.bus}: nmt {cmd.word}: no node {node} on it "
                           f"(nodes {', '.join(str(n) for n in sorted(ev.nodes))})")
        if not running:
            raise BusError(f"canopen bus {ev.bus} is not running: nmt {cmd.word} {node} not "
                           f"sent")
        with managed.lock:
            lc = managed.lifecycle
            before, nmt = lc.state, lc.nmt
        try:
            managed.send_nmt(cmd)
        except can.CanError as exc:
            raise BusError(f"canopen bus {ev.bus}: nmt {cmd.word} {node} not sent: "
                           f"{exc}") from exc
        with managed.lock:
            lc.host_command(cmd, ev.host.now())
            managed.starting = False
        ev.judge(managed, f"the host's nmt {cmd.word}")
        said = "" if nmt is None else f", heartbeat {nmt.text}"
        return f"nmt {cmd.word} sent to {ev.where(managed)} (it was {before.value}{said})"
