"""table - the entries of the device table by name, and which machines this process drives: what
Devtab and each of its parts (health, command checks, write tracking) look devices up in."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator

from chcos.devices.entry import DeviceEntry
from chcos.devices.spec import DeviceMap
from chcos.errors import DeviceError


class DeviceTable:
    """Device entries by name; ``local`` are the machines whose devices this process drives
    (None: all of them). Entries are added by :meth:`load` only, on the kernel thread before
    the drivers start; lookups are safe from any thread."""

    def __init__(self, local: Iterable[int] | None = None) -> None:
        self._entries: dict[str, DeviceEntry] = {}
        self._local = frozenset(local) if local is not None else None
        #: the entry called ``name``, or None (the dict's own lookup: readings and commands
        #: look a device up this way)
        self.find: Callable[[str], DeviceEntry | None] = self._entries.get

    def load(self, devmap: DeviceMap) -> None:
        """Enter every device of ``devmap``; raises DeviceError (nothing entered) if a name is
        already in the table."""
        clash = [d.name for d in devmap.devices if d.name in self._entries]
        if clash:
            raise DeviceError(f"device(s) already in Devtab: {', '.join(clash)}")
        for spec in devmap.devices:
            self._entries[spec.name] = DeviceEntry(spec)

    def get(self, name: str) -> DeviceEntry:
        """The entry called ``name``; raises DeviceError naming it if there is none."""
        e = self._entries.get(name)
        if e is None:
            raise DeviceError(f"no device named {name!r} in Devtab")
        return e

    def is_local(self, machine: int) -> bool:
        """True if ``machine``'s devices are driven by this process."""
        local = self._local
        return local is None or machine in local

    def local_safe_actuators(self) -> list[DeviceEntry]:
        """Every actuator of this process that has a safe value, in table order."""
        return [e for e in self._entries.values()
                if not e.is_sensor and e.spec.safe_value is not None
                and self.is_local(e.spec.machine)]

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def __iter__(self) -> Iterator[DeviceEntry]:
        return iter(self._entries.values())

    def __len__(self) -> int:
        return len(self._entries)
