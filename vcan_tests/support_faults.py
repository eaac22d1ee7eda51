"""Helpers of the bus-fault tests: a wall-clock-bounded run of a virtual-time System, and the
pyModbusTCP server process that can be killed, frozen and restarted (:class:`ModbusPeer`, from
tools/peers.py, which the fault benchmark shares)."""

from __future__ import annotations

import time
from collections.abc import Callable

from chcos.system.embedded import System
from tools.peers import WAIT, ModbusPeer, PeerWrite

__all__ = ["WAIT", "ModbusPeer", "PeerWrite", "run_until"]


def run_until(system: System, pred: Callable[[], bool], step: float = 0.05,
              wall: float = WAIT) -> bool:
    """Run ``system`` on its virtual clock in ``step`` slices until ``pred()`` holds; False if
    it does not within ``wall`` seconds of wall-clock time (real peers reconnect in real
    time)."""
    deadline = time.monotonic() + wall
    while not pred():
        if time.monotonic() > deadline:
            return False
        system.run_for(step)
    return True
