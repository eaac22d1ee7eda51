"""modbus_direct - the in-process hand-off point between a Modbus driver and a simulated slave.

A simulated slave in the same process registers itself under a name (:func:`register`); a bus
whose ``direct`` option names it reaches the slave through :meth:`DirectSlave.exchange`: the
exact bytes a real bus would carry (a Modbus TCP ADU with its MBAP header, an RTU frame with its
CRC) handed over in a call, the answer (or silence) handed back, on the calling thread - no
socket, no thread, no event loop. The table is process-local, as python-can's ``virtual``
channels are; names are unique per simulation (see :func:`chcos.apps.sim.from_map.simulate`).
No I/O here: the driver's transport is :mod:`drivers.modbus.transport`.
"""

from __future__ import annotations

from typing import Literal, Protocol

Framing = Literal["tcp", "rtu"]


class DirectSlave(Protocol):
    """A slave reached in-process."""

    #: the bytes it takes and gives: ``"tcp"`` (MBAP ADUs) or ``"rtu"`` (frames with CRC)
    framing: Framing

    def accepts(self) -> bool:
        """Whether a connection to it would be taken now (a TCP server that was stopped
        refuses it; a serial line is always there)."""

    def exchange(self, adu: bytes, now: float) -> bytes | None:
        """Handle one request ``adu`` at clock time ``now``: the answer's bytes, or None for no
        answer (another unit, a broadcast, a silenced slave)."""


_SLAVES: dict[str, DirectSlave] = {}


def register(name: str, slave: DirectSlave) -> None:
    """Make ``slave`` reachable as ``direct = name``; raises ValueError if the name is taken."""
    if name in _SLAVES:
        raise ValueError(f"a direct Modbus slave named {name!r} exists already")
    _SLAVES[name] = slave


def unregister(name: str) -> None:
    """Forget the slave ``name`` (nothing if there is none)."""
    _SLAVES.pop(name, None)


def lookup(name: str) -> DirectSlave | None:
    """The slave registered as ``name``, None if there is none."""
    return _SLAVES.get(name)
