"""Helpers of the bus-fault tests: a wall-clock-bounded run of a virtual-time System, and the
pyModbusTCP server process that can be killed, frozen and restarted (:class:`ModbusPeer`, from
tools/peers.py, which the fault benchmark shares)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from chcos.system.embedded import System
from tools.peers import WAIT, ModbusPeer, PeerWrite

__all__ = ["WAIT", "ModbusPeer", "PeerWrite", "run_until", "wait_until"]


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


def wait_until(pred: Callable[[], object], timeout: float = WAIT) -> bool:
    """Wait in wall-clock time until ``pred()`` holds, looking every 10 ms (for what another
    thread or process does: a peer's log, counts kept on a library's threads); False if it does
    not within ``timeout`` seconds. The caller asserts, naming what it waited for."""
    pause = threading.Event()
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            return False
        pause.wait(0.01)
    return True
