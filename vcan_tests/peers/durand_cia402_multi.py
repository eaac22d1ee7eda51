"""durand_cia402_multi - an independent two-axis CiA 402 drive on durand: one CANopen node, axis 0
at 0x6040... and axis 1 at 0x6840... (the 0x800 offset of CiA 402 multi-axis drives), each axis
with its own power state machine, motion and faults (vcan_tests/peers/durand_cia402.py's, shifted),
sharing the node's PDOs as a vendor two-axis drive maps them:

* RPDO1 0x6040 + 0x6060 + 0x607A, RPDO2 0x6040 + 0x60FF (axis 0),
* RPDO3 0x6840 + 0x6860 + 0x687A, RPDO4 0x6840 + 0x68FF (axis 1),
* TPDO1 0x6041 + 0x6061 + 0x603F, TPDO2 0x6064 + 0x606C (axis 0),
* TPDO3 0x6841 + 0x6861 + 0x683F, TPDO4 0x6864 + 0x686C (axis 1), all on change.

:func:`two_axis_eds` is the EDS a master uses for it.
"""

from __future__ import annotations

from collections.abc import Callable

from vcan_tests.peers.durand_cia402 import DurandCia402Drive
from vcan_tests.support_cia402 import DRIVE_OBJECTS, drive_eds

RPDOS = ((0x6040, 0x6060, 0x607A), (0x6040, 0x60FF), (0x6840, 0x6860, 0x687A), (0x6840, 0x68FF))
TPDOS = ((0x6041, 0x6061, 0x603F), (0x6064, 0x606C), (0x6841, 0x6861, 0x683F), (0x6864, 0x686C))


class TwoAxisDrive:
    """A two-axis CiA 402 drive (node ``node_id``) on virtual channel ``channel``:
    :attr:`axes` are its two :class:`DurandCia402Drive` axes (their ``received``, ``log``,
    ``history``, ``state``, faults), stepped together by :meth:`step`."""

    def __init__(self, channel: str, node_id: int = 5, *, quick_stop_option: int = 2) -> None:
        first = DurandCia402Drive(channel, node_id, quick_stop_option=quick_stop_option,
                                  pdos=False)
        second = DurandCia402Drive(channel, node_id, quick_stop_option=quick_stop_option,
                                   axis=1, host=first, pdos=False)
        self.axes = (first, second)
        node = first.node
        for n, mapped in enumerate(RPDOS):
            node.rpdo[n].mapping = [(index, 0) for index in mapped]
        for n, mapped in enumerate(TPDOS):
            node.tpdo[n].mapping = [(index, 0) for index in mapped]

    def step(self, dt: float) -> None:
        """Advance both axes by ``dt`` seconds."""
        for axis in self.axes:
            axis.step(dt)

    def wait(self, predicate: Callable[[], bool], timeout: float = 10.0) -> bool:
        """Block until ``predicate()`` holds (checked on every change of either axis)."""
        return self.axes[0].wait(predicate, timeout)

    def close(self) -> None:
        """Stop the node's notifier and close its bus."""
        for axis in reversed(self.axes):
            axis.close()


def two_axis_eds() -> str:
    """The EDS of :class:`TwoAxisDrive`: the CiA 402 objects of both axes and its PDOs."""
    second = tuple((index + 0x800, f"Axis 1 {name}", dtype, access, default)
                   for index, name, dtype, access, default in DRIVE_OBJECTS)
    return drive_eds(name="Two-axis CiA 402 drive", rpdos=RPDOS, tpdos=TPDOS, extra=second)
