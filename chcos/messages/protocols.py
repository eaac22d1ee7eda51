"""protocols - what the message manager asks of its collaborators: the device table below it
and the communications manager beside it, each as a narrow protocol given at construction.

:class:`NoComm` stands for the communications manager in a one-process system (every machine
is local): there is nobody else to tell, and a link to another machine is an error.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any, Protocol

from chcos.devices.entry import DeviceStatus
from chcos.errors import MessageError
from chcos.tables.messages import Link
from chcos.tables.tasks import TaskEntry


class Devices(Protocol):
    """What the message manager and the user API ask of the device table
    (:class:`chcos.devices.devtab.Devtab`)."""

    def write(self, device: str, value: Any, source: str = "host") -> None:
        """Command an actuator; raises DeviceError if it refuses."""

    def check_readable(self, device: str) -> None:
        """Raise SensorFailure if sensor ``device`` is failed or stale."""

    def healthy(self, device: str) -> bool:
        """Whether ``device`` delivers (neither failed nor stale)."""

    def safe_values(self, devices: Iterable[str], why: str = "abnormal completion") -> int:
        """Write the safe value of each of ``devices`` that has one; returns how many."""

    def estop(self, reason: str) -> int:
        """Safe values on every local actuator; returns how many."""


class Comm(Protocol):
    """What the message manager asks of the communications manager when a link leads to another
    satellite (see :mod:`chcos.comm.manager`). Every call is made on the kernel thread and must not
    block."""

    def sensory(self, link: Link, value: Any) -> bool:
        """Carry a sensory message to the destination's satellite; True if it replaced one of
        the link's still waiting to leave."""

    def tap(self, link: Link, source: str, value: Any) -> None:
        """Carry a tapped sensory message to a remote exception task."""

    def open(self, link: Link, command: Any, wait: bool) -> None:
        """Ask the target's satellite to invoke it for ``link``'s caller."""

    def close(self, link: Link) -> None:
        """Ask the target's satellite to release it from ``link``'s caller."""

    def report(self, link: Link) -> None:
        """Send ``link``'s new status (completion, pre-emption) to the caller's satellite."""

    def granted(self, link: Link) -> None:
        """Tell the caller's satellite that ``link``'s caller now owns the target."""

    def actuator(self, device: str, machine: int, value: Any, source: str) -> None:
        """Carry an actuator command to the device's satellite."""

    def device_status(self, device: str, status: DeviceStatus, reason: str) -> None:
        """Tell every satellite that a local device changed status."""

    def estop(self, reason: str) -> None:
        """Emergency stop on every other satellite, at top priority."""

    def is_up(self, machine: int) -> bool:
        """Whether satellite ``machine`` is on the link now."""

    def query(self, link: Link, asker: TaskEntry, peer: TaskEntry, qid: int, topic: str,
              args: list[Any]) -> None:
        """Carry ``asker``'s world-model query ``qid`` to ``peer``'s satellite (on ``link``, a
        link joining the two). Raises MessageError if it cannot be encoded or sent."""


class NoComm:
    """The communications manager of a one-process system: no other satellite is up, status
    changes and e-stops have nobody else to reach, and a message for another machine raises
    MessageError naming it (a link can only lead there when the tables say a machine is not
    local, which a one-process system never does)."""

    def _refuse(self, what: str, machine: int) -> None:
        raise MessageError(f"{what} for machine {machine}: this system has no link to other "
                           f"satellites (no communications manager)")

    def sensory(self, link: Link, value: Any) -> bool:
        """Refused: see the class."""
        self._refuse(f"sensory message on {link.name}", link.dst_machine)
        return False

    def tap(self, link: Link, source: str, value: Any) -> None:
        """Refused: see the class."""
        self._refuse(f"tapped message on {link.name}", link.dst_machine)

    def open(self, link: Link, command: Any, wait: bool) -> None:
        """Refused: see the class."""
        self._refuse(f"invoke on {link.name}", link.dst_machine)

    def close(self, link: Link) -> None:
        """Refused: see the class."""
        self._refuse(f"close on {link.name}", link.dst_machine)

    def report(self, link: Link) -> None:
        """Refused: see the class."""
        self._refuse(f"completion on {link.name}", link.src_machine)

    def granted(self, link: Link) -> None:
        """Refused: see the class."""
        self._refuse(f"ownership on {link.name}", link.src_machine)

    def actuator(self, device: str, machine: int, value: Any, source: str) -> None:
        """Refused: see the class."""
        self._refuse(f"actuator command to {device}", machine)

    def device_status(self, device: str, status: DeviceStatus, reason: str) -> None:
        """Nobody else to tell."""

    def estop(self, reason: str) -> None:
        """Nobody else to stop."""

    def is_up(self, machine: int) -> bool:
        """No other satellite is ever up."""
        return False

    def query(self, link: Link, asker: TaskEntry, peer: TaskEntry, qid: int, topic: str,
              args: list[Any]) -> None:
        """Refused: see the class."""
        self._refuse(f"world-model query of {asker.name}", peer.machine)
