"""canopen_remote - one remote CANopen node as the ``canopen`` driver manages it: an object
composing canopen's ``RemoteNode`` (its SDO client, PDO maps, NMT and EMCY parts) with the
node's lifecycle (:mod:`drivers.canopen_lifecycle`), its boot configuration
(:mod:`drivers.canopen_config`), heartbeat supervision, the RPDO images and its devices; and the
boot procedure the driver's I/O thread runs for it (identity, error register, configuration
download with read-back, RPDO images seeded from the node). Failures are returned as typed
outcomes, never raised; what they mean for the node's devices is the driver's business
(:mod:`drivers.canopen_node`).
"""

from __future__ import annotations

import struct
import threading
import time
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

from canopen.sdo.client import SdoClient
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from drivers.canopen_config import NodeConfig, SdoWrite
from drivers.canopen_lifecycle import Lifecycle, NmtCommand, NmtState
from drivers.canopen_od import coerce

#: the client command specifiers of the SDO requests that name an object (CiA 301 7.2.4.3:
#: initiate download 1, initiate upload 2; the driver makes no block transfers, whose
#: sub-block frames carry a sequence number where a specifier would be)
_NAMING_REQUESTS = (1, 2)
#: the client command specifier of an abort transfer request
_ABORT = 4


class ObjectSdoClient(SdoClient):
    """canopen's SDO client whose abort transfer requests name the object of the transfer they
    abort (CiA 301 7.2.4.3.17: multiplexer = index and sub-index), as a server needs to tell
    which transfer ended; canopen's own sends 0x0000:00. The object is the one the last
    initiate request named (segments carry none)."""

    def __init__(self, rx_cobid: int, tx_cobid: int, od: Any) -> None:
        super().__init__(rx_cobid, tx_cobid, od)  # type: ignore[no-untyped-call]
        self._mux = b"\x00\x00\x00"

    def send_request(self, request: bytes | bytearray) -> None:
        """Send ``request``, remembering the object it names (an initiate request)."""
        if request and (request[0] >> 5) in _NAMING_REQUESTS and len(request) >= 4:
            self._mux = bytes(request[1:4])
        super().send_request(request)  # type: ignore[no-untyped-call]

    def abort(self, abort_code: int = 0x08000000) -> None:
        """Abort the transfer in progress: abort code ``abort_code`` for its object."""
        request = bytearray(8)
        request[0] = _ABORT << 5
        request[1:4] = self._mux
        struct.pack_into("<L", request, 4, abort_code)
        super().send_request(request)  # type: ignore[no-untyped-call]


def use_object_sdo_client(remote: Any) -> None:
    """Give ``remote`` (a canopen ``RemoteNode`` not yet on a network) an
    :class:`ObjectSdoClient` as its SDO channel."""
    client = ObjectSdoClient(0x600 + remote.id, 0x580 + remote.id, remote.object_dictionary)
    remote.sdo_channels = [client]
    remote.sdo = client


class RpdoImages:
    """The frames of a node's enabled RPDOs, composed from the current value of every object they
    map: an object mapped into several RPDOs is written into each of their images, so sending
    one PDO never carries a stale copy of an object another PDO wrote (CiA 402 drives map the
    controlword 0x6040 into RPDO1 and, with 0x6060, into RPDO2). Used by one thread at a time
    (the driver's I/O thread)."""

    def __init__(self, remote: Any) -> None:
        self._vars: dict[tuple[int, int], list[Any]] = {}
        for pdo_map in remote.rpdo.map.values():
            if pdo_map.enabled:
                for var in pdo_map.map:
                    self._vars.setdefault((var.index, var.subindex), []).append(var)

    def objects(self) -> list[tuple[int, int]]:
        """Every object mapped into an enabled RPDO."""
        return list(self._vars)

    def pdos_of(self, index: int, subindex: int) -> list[Any]:
        """The RPDO maps carrying ``index``:``subindex``, in PDO order."""
        return [v.pdo_parent for v in self._vars.get((index, subindex), ())]

    def set(self, index: int, subindex: int, data: bytes) -> None:
        """The object's new encoded value, into every image that maps it."""
        for var in self._vars.get((index, subindex), ()):
            var.set_data(data)


class BootOutcome(Enum):
    """How the boot procedure of a node ended."""

    CONFIGURED = "configured"         # identity right, every write read back
    SILENT = "no answer"              # an SDO timed out: the node is not there (yet)
    IDENTITY_MISMATCH = "identity mismatch"
    CONFIG_REFUSED = "configuration refused"


@dataclass(frozen=True)
class BootResult:
    """The outcome, the reason (naming the object and both values where they differ) and the
    error register 0x1001 as read at this boot (None if the node has no 0x1001)."""

    outcome: BootOutcome
    reason: str = ""
    error_register: int | None = None
    #: with ``store_config``: True if the configuration was stored (0x1010 answered), False
    #: if the node already held all of it (nothing to store); None without ``store_config``
    stored: bool | None = None


@dataclass
class ManagedNode:
    """A node of the bus (see the module doc). ``lock`` guards the lifecycle and the heartbeat
    fields, which the reader, the watchdog and the I/O thread all touch."""

    remote: Any
    config: NodeConfig
    heartbeat_timeout: float | None
    lifecycle: Lifecycle
    images: RpdoImages
    devices: list[str] = field(default_factory=list)
    #: the CiA 402 axes it hosts (their actuators' names): the drive's faults are theirs,
    #: judged from the statusword, so EMCY and the error register do not fail the node
    axes: list[str] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)
    last_heartbeat: float = field(default_factory=time.monotonic)
    lost: bool = False
    #: True until the first boot procedure after the driver's start ended: meanwhile a node that
    #: is not ready yet does not fail its devices (it is being brought up)
    starting: bool = True
    #: True while a boot procedure is queued or running: heartbeat supervision waits (a node
    #: that rebooted without its stored configuration has no heartbeat until it is configured)
    booting: bool = True
    #: when a silent node's heartbeat may start its boot procedure again (monotonic s)
    retry_at: float = 0.0
    #: when the next restart of the recovery policy may go out (host clock; None: not armed)
    retry_at_host: float | None = None
    #: the NMT state of the last heartbeat (None before one): a change asks its axes to read
    #: their drive
    last_nmt: NmtState | None = None
    #: devices that are a CiA 402 drive's controlword (0x6040 of an axis) in a plain map: a
    #: fatal EMCY does not fail them, so that the fault reset can be written
    controlwords: tuple[str, ...] = ()

    @property
    def id(self) -> int:
        return int(self.remote.id)

    def where(self, bus: str) -> str:
        return f"canopen node {self.id} on bus {bus}"

    def send_nmt_start(self) -> None:
        """Send the NMT start command to this node (raises ``can.CanError``)."""
        self.send_nmt(NmtCommand.START)

    def send_nmt(self, command: NmtCommand) -> None:
        """Send NMT ``command`` to this node (COB-ID 0x000; raises ``can.CanError``)."""
        self.remote.network.send_message(0, bytes((int(command), self.id)))

    # -- the boot procedure (driver's I/O thread) ---------------------------------------------

    def upload_uint(self, index: int, subindex: int) -> int:
        """An unsigned object read by SDO (raises the canopen SDO errors)."""
        return int.from_bytes(self.remote.sdo.upload(index, subindex), "little")

    def read_error_register(self) -> int | None:
        """0x1001 by SDO; None if the node refuses it (raises SdoCommunicationError)."""
        try:
            return self.upload_uint(0x1001, 0)
        except SdoAbortedError:
            return None

    def boot(self, master_id: int) -> BootResult:
        """Identity check, error register, configuration download with read-back, RPDO images
        from the node's values. Raises ``can.CanError`` if a request cannot be sent."""
        try:
            if (why := self._check_identity()) is not None:
                return BootResult(BootOutcome.IDENTITY_MISMATCH, why)
            with self.lock:
                self.lifecycle.identity_checked()
            error_register = self.read_error_register()
            writes = self.config.writes(self.remote.object_dictionary, self.id, master_id)
            store = self.config.store()
            # with store_config: whether the node already holds the configuration (it came up
            # with it stored), asked before the download changes anything
            held = store is not None and self._holds(writes)
            for w in writes:
                if (why := self._download(w)) is not None:
                    return BootResult(BootOutcome.CONFIG_REFUSED, why, error_register)
            stored: bool | None = None
            if store is not None:
                stored = not held
                if stored and (why := self._download(store)) is not None:
                    return BootResult(BootOutcome.CONFIG_REFUSED, why, error_register)
            self._seed_images()
        except SdoCommunicationError as exc:
            return BootResult(BootOutcome.SILENT, f"no SDO answer: {exc}")
        return BootResult(BootOutcome.CONFIGURED, "", error_register, stored)

    def _holds(self, writes: list[SdoWrite]) -> bool:
        """True if the node already holds the value each object ends with after ``writes``
        (read by SDO; an object that cannot be read back, or refuses the upload, counts as not
        held). Raises SdoCommunicationError if the node does not answer."""
        final: dict[tuple[int, int], SdoWrite] = {}
        for w in writes:
            final[(w.index, w.subindex)] = w
        for w in final.values():
            if not w.read_back:
                return False
            try:
                want = self._encode(w)
                back = self.remote.sdo.upload(w.index, w.subindex)
            except SdoAbortedError:
                return False
            except (struct.error, ValueError, TypeError, OverflowError):
                return False        # the download reports it
            mask = ~w.ignore_mask
            if len(back) < len(want) or (int.from_bytes(back[:len(want)], "little") & mask
                                         != int.from_bytes(want, "little") & mask):
                return False
        return True

    def _check_identity(self) -> str | None:
        ident = self.config.identity
        if ident is None:
            return None
        for sub, name, want in ident.fields():
            try:
                got = self.upload_uint(0x1018, sub)
            except SdoAbortedError as exc:
                return f"identity 0x1018:{sub:02X} ({name}) not readable: {exc}"
            if got != want:
                return (f"identity mismatch: {name} (0x1018:{sub:02X}) is 0x{got:08X} on the "
                        f"node, 0x{want:08X} in the map")
        return None

    def _encode(self, w: SdoWrite) -> bytes:
        if w.bits is not None:
            return int(w.value).to_bytes(w.bits // 8, "little")
        var = self.remote.object_dictionary.get_variable(w.index, w.subindex)
        return bytes(var.encode_raw(coerce(var, w.value)))

    def _download(self, w: SdoWrite) -> str | None:
        """One configuration write and its read-back; why it failed, or None."""
        where = f"0x{w.index:04X}:{w.subindex:02X} ({w.what})"
        try:
            data = self._encode(w)
        except (struct.error, ValueError, TypeError, OverflowError) as exc:
            return f"configuration write {where} = {w.value!r}: cannot encode: {exc}"
        try:
            self.remote.sdo.download(w.index, w.subindex, data)
        except SdoAbortedError as exc:
            return f"configuration write {where} = {w.value!r} aborted: {exc}"
        if not w.read_back:
            return None
        try:
            back = self.remote.sdo.upload(w.index, w.subindex)
        except SdoAbortedError as exc:
            return f"configuration read-back of {where} aborted: {exc}"
        mask = ~w.ignore_mask
        got = int.from_bytes(back[:len(data)], "little")
        want = int.from_bytes(data, "little")
        if len(back) < len(data) or got & mask != want & mask:
            return (f"configuration read-back of {where}: wrote {want:#x}, the node holds "
                    f"{got:#x}")
        return None

    def _seed_images(self) -> None:
        """Every RPDO-mapped object's current value from the node into the images, so the
        first RPDO sent carries the node's values for the objects nobody wrote yet."""
        od = self.remote.object_dictionary
        for index, sub in self.images.objects():
            var = od.get_variable(index, sub)
            if var is None or not var.readable:
                continue
            try:
                data = self.remote.sdo.upload(index, sub)
            except SdoAbortedError:
                continue
            self.images.set(index, sub, bytes(data))
