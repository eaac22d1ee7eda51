"""support_canopen_node - a durand node (:class:`vcan_tests.peers.durand_node.DurandNode`) given
what CiA 301 asks of a real node beside durand's own objects, for the CANopen driver's tests:

* **store parameters** (0x1010:01..03, CiA 301 7.5.2.13): a download of the "save" signature
  0x65766173 keeps the node's heartbeat producer time and PDO mappings over a power cycle (its
  :attr:`stored`); any other value is refused (abort 0x08000020) and stores nothing; reading a
  sub-index gives the storage capability (1: saves on command), as on a real node;
* a **heartbeat consumer** (0x1016:01 = producer node id << 16 | time in ms, CiA 301 7.2.8.3.2):
  armed by the producer's first heartbeat after the entry is set, it declares the producer lost
  when no heartbeat came within the time, sends EMCY 0x8130 (heartbeat error, error register
  communication bit) and applies the error behaviour 0x1029:01 (0 PRE-OPERATIONAL if it was
  OPERATIONAL, 1 no change, 2 STOPPED); the producer's first heartbeat after that is an event.

Every such happening is recorded in :attr:`Cia301Node.events` (and told to ``on_event``).
Run as a process (``python -m vcan_tests.support_canopen_node --interface udp_multicast
--channel 239.x.y.z --node 5 --eds node.eds``) the node lives on any python-can interface,
writes its EDS, prints ``ready`` and then one line per event, until its standard input closes:
the peer of the tests whose controller is another process.
"""

from __future__ import annotations

import argparse
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
from durand import Variable
from durand.datatypes import DatatypeEnum as DT
from durand.object_dictionary import Record
from durand.scheduler import get_scheduler
from durand.services.nmt import StateEnum

from vcan_tests.peers.durand_node import DurandNode, GatedNetwork, Stored

#: the "save" signature of 0x1010 (the characters s, a, v, e, little-endian)
SAVE = 0x65766173
#: EMCY error code of a heartbeat consumer timeout (CiA 301 table 26: "heartbeat error")
EMCY_HEARTBEAT = 0x8130
#: error register bit "communication error" (CiA 301 7.5.2.2)
REGISTER_COMMUNICATION = 0x11


class Cia301Node(DurandNode):
    """A durand node with store parameters and a heartbeat consumer (see the module doc).
    ``bus`` the python-can arguments of its bus (default: the virtual ``channel``)."""

    def __init__(self, channel: str, node_id: int, *, bus: dict[str, Any] | None = None,
                 on_event: Callable[[str], None] | None = None, **kw: Any) -> None:
        self.bus_args = bus or {"interface": "virtual", "channel": channel}
        self.on_event = on_event
        self.events: list[str] = []
        self._events_lock = threading.Lock()
        #: stores done ("save" accepted), consumer losses declared
        self.saves = 0
        self.consumer_losses = 0
        #: master heartbeats received since the consumer was last armed
        self.master_beats = 0
        self._beat = 0                      # the heartbeat a consumer timer was armed for
        self._watched: int | None = None    # the COB-ID the consumer subscribed to
        self._restoring = False             # 0x1010 reads its capability again after a save
        self._lost_unheard = False          # a loss declared, no heartbeat since
        super().__init__(channel, node_id, **kw)

    # -- what happens to it -------------------------------------------------------------------

    def event(self, text: str) -> None:
        with self._events_lock:
            self.events.append(text)
        if self.on_event is not None:
            self.on_event(text)

    def seen(self, text: str) -> bool:
        """True if an event starting with ``text`` happened."""
        with self._events_lock:
            return any(e.startswith(text) for e in self.events)

    # -- life -----------------------------------------------------------------------------------

    def power_on(self, announce: bool = True) -> None:
        """As :meth:`DurandNode.power_on`, on :attr:`bus_args`."""
        bus = can.Bus(**self.bus_args, receive_own_messages=False)
        network = GatedNetwork(bus)
        self._watched = None
        self.node = self._build(network)
        self._bus, self._network = bus, network
        self.boots += 1
        network.open(announce)
        if self.stored.heartbeat_ms:
            self.node.object_dictionary.write(0x1017, 0, self.stored.heartbeat_ms)

    def _build(self, network: Any) -> Any:
        node = super()._build(network)
        od = node.object_dictionary
        store = Record(name="Store parameters")
        for sub, name in ((1, "Save all parameters"), (2, "Save communication parameters"),
                          (3, "Save application parameters")):
            store[sub] = Variable(DT.UNSIGNED32, "rw", 1, name=name)
            od.validate_callbacks[(0x1010, sub)].add(self._check_signature)
            od.validate_callbacks[(0x1010, sub)].add(
                lambda value, mux=(0x1010, sub): self._maybe_abort(mux))   # abort_writes
            od.download_callbacks[(0x1010, sub)].add(lambda value, sub=sub: self._save(sub))
        od[0x1010] = store
        od.download_callbacks[(0x1016, 1)].add(self._consume)
        node.nmt.state_callbacks.add(lambda state: self.event(f"state {StateEnum(state).name}"))
        return node

    # -- store parameters ---------------------------------------------------------------------

    def _check_signature(self, value: int) -> None:
        if value != SAVE and not self._restoring:
            raise ValueError("not the save signature")     # durand answers 0x08000020

    def _save(self, sub: int) -> None:
        """Keep the heartbeat time and the PDO mappings (what :class:`Stored` holds); the
        sub-index reads its capability again."""
        od = self.node.object_dictionary

        def mapping(base: int, count: int) -> dict[int, list[tuple[int, int]]]:
            out = {}
            for i in range(count):
                n = od.read(base + i, 0)
                if n:
                    out[i + 1] = [(e >> 16, (e >> 8) & 0xFF)
                                  for e in (od.read(base + i, k) for k in range(1, n + 1))]
            return out

        self.stored = Stored(heartbeat_ms=od.read(0x1017, 0),
                             rpdo=mapping(0x1600, len(self.node.rpdo)),
                             tpdo=mapping(0x1A00, len(self.node.tpdo)))
        self._restoring = True
        try:
            od.write(0x1010, sub, 1)
        finally:
            self._restoring = False
        self.saves += 1
        self.event(f"saved 0x1010:{sub:02X}")

    # -- heartbeat consumer -------------------------------------------------------------------

    def _consume(self, entry: int) -> None:
        """0x1016:01 was downloaded: watch node ``entry >> 16``'s heartbeat (0 ms: no more)."""
        network = self._network if self._network is not None else self.node.network
        if self._watched is not None:
            network.remove_subscription(self._watched)
            self._watched = None
        producer, ms = (entry >> 16) & 0x7F, entry & 0xFFFF
        self._beat += 1                         # a timer armed before is void
        if producer and ms:
            self._watched = 0x700 + producer
            self.master_beats = 0
            network.add_subscription(self._watched, lambda cob, msg: self._heartbeat(ms))
            self.event(f"consumer of node {producer} every {ms} ms")

    def _heartbeat(self, ms: int) -> None:
        """A heartbeat of the watched producer: (re)arm the consumer's timer."""
        self.master_beats += 1
        self._beat += 1
        if self.master_beats == 1:
            self.event("consumer armed")
        if self._lost_unheard:
            self._lost_unheard = False
            self.event("producer heartbeat back")
        get_scheduler().add(ms / 1000.0, self._timeout, args=(self._beat,))

    def _timeout(self, armed: int) -> None:
        if armed != self._beat:
            return                              # a heartbeat came meanwhile
        self.consumer_losses += 1
        self._lost_unheard = True
        self.event(f"producer heartbeat lost after {self.master_beats} heartbeats")
        self.node.emcy.set(EMCY_HEARTBEAT, REGISTER_COMMUNICATION)
        self.event(f"emcy 0x{EMCY_HEARTBEAT:04X}")
        behaviour = self.node.object_dictionary.read(0x1029, 1)
        if behaviour == 0 and self.state == StateEnum.OPERATIONAL:
            self.node.nmt.set_state(StateEnum.PRE_OPERATIONAL)
        elif behaviour == 2:
            self.node.nmt.set_state(StateEnum.STOPPED)


def main(argv: list[str] | None = None) -> int:
    """The node as a process (see the module doc)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--interface", required=True)
    ap.add_argument("--channel", required=True)
    ap.add_argument("--node", type=int, required=True)
    ap.add_argument("--eds", type=Path, required=True)
    args = ap.parse_args(argv)

    def say(text: str) -> None:
        print(text, flush=True)

    node = Cia301Node(args.channel, args.node, on_event=say,
                      bus={"interface": args.interface, "channel": args.channel})
    try:
        node.write_eds(args.eds)
        say("ready")
        for _ in sys.stdin:
            pass
    finally:
        node.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
