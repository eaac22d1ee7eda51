"""The host's ``nmt`` command in a system of satellites (issue 46): the line goes from the host
session to the satellite that drives the bus (the machine of its devices) on its authenticated
control key, and reaches the independent durand drive there; without the bus named the host
refuses it (it cannot tell which satellite drives the node). The two-satellite cell of
:mod:`vcan_tests.test_cia402_satellites` (real link on loopback, sealed)."""

from __future__ import annotations

import pytest

from chcos.errors import InstallError
from vcan_tests.support_faults import wait_until
from vcan_tests.test_cia402_satellites import NODE, Cell, cell

__all__ = ["cell"]      # the fixture


def test_the_host_sends_nmt_to_the_satellite_driving_the_bus(cell: Cell) -> None:
    host, drive = cell.host, cell.drive
    answer = host.execute(f"nmt stop {NODE} drives")
    assert answer.startswith(f"nmt stop sent to canopen node {NODE} on bus drives (it was ")
    assert wait_until(lambda: drive.node.nmt.state == 4)            # STOPPED, as it says
    assert host.execute(f"nmt start {NODE} drives").startswith("nmt start sent")
    assert wait_until(lambda: drive.node.nmt.state == 5)            # OPERATIONAL
    with pytest.raises(InstallError, match="name the bus"):
        host.execute(f"nmt stop {NODE}")
    with pytest.raises(InstallError, match="no device on bus 'nope'"):
        host.execute(f"nmt stop {NODE} nope")
