"""sdo_server - the SDO server of a simulated CANopen node (CiA 301) as a pure state machine:
request bytes and the node's time in, response bytes out.

:meth:`SdoServer.receive` takes the data of one frame on the node's request COB-ID (0x600+id)
and returns the data of the frames to answer with (on 0x580+id); :meth:`SdoServer.expire`
aborts a transfer the client left unfinished once :attr:`SdoServer.deadline` has passed
(0x05040000). Expedited, segmented and block transfers work both ways, block transfers with
the CRC of CiA 301 (CRC-16-CCITT, polynomial 0x1021, initial value 0: ``binascii.crc_hqx``)
and the protocol switch threshold. What an object allows is the :class:`Dictionary`'s to say
(it raises :class:`SdoAbort` with the code); the server owns the protocol:

* a frame that is not 8 bytes long is not an SDO (ignored, as CANopenNode does);
* a client abort (``80 ...``) ends the transfer in progress without an answer;
* a segment, a block sub-command or an unknown command specifier with no transfer in
  progress: abort 0x05040001 on index 0000 sub-index 00 (no transfer is named);
* in a transfer, any frame its protocol does not expect (another initiate included):
  abort 0x05040001 naming that transfer, which ends; the new request is not served;
* a toggle bit that did not alternate: 0x05030000; a block size outside 1..127: 0x05040002;
  a block sequence number 0 or above the block size, or an acknowledgement of segments not
  sent: 0x05040003; a CRC that does not match: 0x05040004; more data than
  :data:`MAX_DOWNLOAD` for an object of no fixed size: 0x05040005;
* a download whose byte count differs from the size the client indicated: 0x06070010
  (the object's own length rules, 0x06070012/0x06070013, are the dictionary's);
* every abort carries the index and sub-index of the transfer it ends, never an earlier one.
"""

from __future__ import annotations

import binascii
import enum
import struct
from dataclasses import dataclass, field
from typing import Protocol


class AbortCode(enum.IntEnum):
    """The SDO abort codes of CiA 301 the simulated node sends."""

    TOGGLE = 0x05030000          # toggle bit not alternated
    TIMEOUT = 0x05040000         # SDO protocol timed out
    COMMAND = 0x05040001         # client/server command specifier not valid or unknown
    BLOCK_SIZE = 0x05040002      # invalid block size (block mode only)
    SEQUENCE = 0x05040003        # invalid sequence number (block mode only)
    CRC = 0x05040004             # CRC error (block mode only)
    OUT_OF_MEMORY = 0x05040005   # out of memory
    UNSUPPORTED = 0x06010000     # unsupported access to an object
    WRITE_ONLY = 0x06010001      # attempt to read a write-only object
    READ_ONLY = 0x06010002       # attempt to write a read-only object
    NO_OBJECT = 0x06020000       # object does not exist in the object dictionary
    NOT_MAPPABLE = 0x06040041    # object cannot be mapped to the PDO
    PDO_LENGTH = 0x06040042      # number and length of objects would exceed the PDO length
    INCOMPATIBLE = 0x06040043    # general parameter incompatibility
    LENGTH = 0x06070010          # data type does not match, length does not match
    TOO_LONG = 0x06070012        # data type does not match, length too high
    TOO_SHORT = 0x06070013       # data type does not match, length too low
    NO_SUBINDEX = 0x06090011     # sub-index does not exist
    VALUE = 0x06090030           # invalid value for parameter (download only)
    TOO_HIGH = 0x06090031        # value of parameter written too high
    TOO_LOW = 0x06090032         # value of parameter written too low
    GENERAL = 0x08000000         # general error
    NOT_STORED = 0x08000020      # data cannot be transferred or stored to the application
    DEVICE_STATE = 0x08000022    # ... because of the present device state
    NO_DATA = 0x08000024         # no data available


class SdoAbort(Exception):
    """A refused SDO access: ``code`` is the abort code the server sends."""

    def __init__(self, code: int) -> None:
        super().__init__(f"SDO abort 0x{code:08X}")
        self.code = code


class Dictionary(Protocol):
    """What the SDO server asks of the node's object dictionary. Each method raises
    :class:`SdoAbort` with the code to send for a refused access."""

    def read(self, index: int, subindex: int) -> bytes:
        """The value of ``index:subindex`` for an upload (existence and access checked)."""

    def open_write(self, index: int, subindex: int) -> int | None:
        """Check a download may start (the object exists and is writable); return its size in
        bytes when fixed, None when it has none (strings, domains)."""

    def write(self, index: int, subindex: int, data: bytes) -> None:
        """Store a downloaded value (length, range and the device's own rules checked)."""


#: The largest value a download of an object without a fixed size may carry, bytes.
MAX_DOWNLOAD = 1 << 16
#: Segments per block this server takes in a block download (the CiA 301 maximum).
BLOCK_SIZE = 127
#: Seconds a transfer may wait for the client's next frame (CANopenNode's default).
TIMEOUT = 1.0


class Phase(enum.Enum):
    """What a transfer in progress waits for from the client."""

    DOWNLOAD_SEGMENT = "download segment"
    UPLOAD_SEGMENT = "upload segment"
    BLOCK_DOWNLOAD = "block download sub-block"
    BLOCK_DOWNLOAD_END = "end block download"
    BLOCK_UPLOAD_START = "start block upload"
    BLOCK_UPLOAD_ACK = "block upload acknowledgement"
    BLOCK_UPLOAD_END = "end block upload response"


@dataclass
class Transfer:
    """A transfer in progress: the object, what comes next and what was moved so far."""

    phase: Phase
    index: int
    subindex: int
    deadline: float
    data: bytearray = field(default_factory=bytearray)
    indicated: int | None = None   # download: the size the client indicated
    fixed: int | None = None       # download: the object's size, when it has a fixed one
    toggle: int = 0
    crc: bool = False              # the client computes (download) or checks (upload) a CRC
    blksize: int = 0
    seqno: int = 0                 # block download: last segment taken; upload: sent in block
    offset: int = 0                # block upload: bytes the client acknowledged

    def mux(self) -> bytes:
        """The multiplexer (index, sub-index) as bytes 1..3 carry it."""
        return struct.pack("<HB", self.index, self.subindex)


def abort_frame(index: int, subindex: int, code: int) -> bytes:
    """An abort transfer frame's data: ``80``, index, sub-index, abort code."""
    return struct.pack("<BHBI", 0x80, index, subindex, code)


def crc16(data: bytes) -> int:
    """The block transfer CRC of CiA 301 (CRC-16-CCITT, initial value 0)."""
    return binascii.crc_hqx(data, 0)


class SdoServer:
    """The SDO server (see the module doc) over ``dictionary``; ``timeout`` seconds of the
    node's clock between the client's frames before a transfer is aborted. Not thread-safe:
    the node calls it under its own lock."""

    def __init__(self, dictionary: Dictionary, timeout: float = TIMEOUT) -> None:
        self._dict = dictionary
        self.timeout = timeout
        self._transfer: Transfer | None = None

    @property
    def deadline(self) -> float | None:
        """When the transfer in progress times out (None: no transfer)."""
        return None if self._transfer is None else self._transfer.deadline

    @property
    def transfer(self) -> Transfer | None:
        """The transfer in progress, if any."""
        return self._transfer

    def reset(self) -> None:
        """Drop a transfer in progress without an answer (the node left PRE-OPERATIONAL and
        OPERATIONAL, or was reset)."""
        self._transfer = None

    def expire(self, now: float) -> list[bytes]:
        """The timeout abort of a transfer whose deadline ``now`` has reached, if any."""
        t = self._transfer
        if t is None or now < t.deadline:
            return []
        self._transfer = None
        return [abort_frame(t.index, t.subindex, AbortCode.TIMEOUT)]

    def receive(self, data: bytes, now: float) -> list[bytes]:
        """Handle one request at time ``now``; return the responses (the data of each frame).
        A transfer that timed out before ``now`` is aborted first."""
        out = self.expire(now)
        if len(data) != 8:
            return out
        if data[0] == 0x80:                        # the client aborts
            self._transfer = None
            return out
        t = self._transfer
        try:
            if t is None:
                out += self._initiate(bytes(data), now)
            else:
                out += self._continue(t, bytes(data), now)
        except SdoAbort as exc:
            t = self._transfer
            self._transfer = None
            index, sub = (t.index, t.subindex) if t is not None else _mux(data)
            out.append(abort_frame(index, sub, exc.code))
        return out

    # -- initiate ------------------------------------------------------------------------------

    def _initiate(self, data: bytes, now: float) -> list[bytes]:
        ccs, cs = data[0] >> 5, data[0]
        if ccs == 1:
            return self._initiate_download(data, now)
        if ccs == 2:
            return self._initiate_upload(data, now)
        if ccs == 6 and not cs & 0x01:
            return self._initiate_block_download(data, now)
        if ccs == 5 and cs & 0x03 == 0:
            return self._initiate_block_upload(data, now)
        # a segment or block sub-command with no transfer, or an unknown specifier
        return [abort_frame(0, 0, AbortCode.COMMAND)]

    def _initiate_download(self, data: bytes, now: float) -> list[bytes]:
        cs = data[0]
        index, sub = _mux(data)
        fixed = self._dict.open_write(index, sub)
        answer = bytes([0x60]) + data[1:4] + bytes(4)
        if cs & 0x02:                              # expedited: the data is in bytes 4..7
            # size indicated in the command, else the object's (up to 4)
            size = 4 - ((cs >> 2) & 0x03) if cs & 0x01 else \
                (fixed if fixed is not None and fixed < 4 else 4)
            self._dict.write(index, sub, data[4:4 + size])
            return [answer]
        t = Transfer(Phase.DOWNLOAD_SEGMENT, index, sub, now + self.timeout, fixed=fixed)
        if cs & 0x01:
            t.indicated = _u32(data, 4)
            self._check_indicated(t)
        self._transfer = t
        return [answer]

    def _check_indicated(self, t: Transfer) -> None:
        """An indicated size the object cannot take is refused at the start."""
        if t.indicated is None:
            return
        if t.fixed is not None and t.indicated != t.fixed:
            self._transfer = t
            raise SdoAbort(AbortCode.TOO_LONG if t.indicated > t.fixed else AbortCode.TOO_SHORT)
        if t.fixed is None and t.indicated > MAX_DOWNLOAD:
            self._transfer = t
            raise SdoAbort(AbortCode.OUT_OF_MEMORY)

    def _initiate_upload(self, data: bytes, now: float) -> list[bytes]:
        index, sub = _mux(data)
        value = self._dict.read(index, sub)
        if 0 < len(value) <= 4:                    # expedited, size indicated
            cs = 0x43 | ((4 - len(value)) << 2)
            return [bytes([cs]) + data[1:4] + value.ljust(4, b"\x00")]
        self._transfer = Transfer(Phase.UPLOAD_SEGMENT, index, sub, now + self.timeout,
                                  data=bytearray(value))
        return [bytes([0x41]) + data[1:4] + struct.pack("<I", len(value))]

    def _initiate_block_download(self, data: bytes, now: float) -> list[bytes]:
        cs = data[0]
        index, sub = _mux(data)
        fixed = self._dict.open_write(index, sub)
        t = Transfer(Phase.BLOCK_DOWNLOAD, index, sub, now + self.timeout, fixed=fixed,
                     crc=bool(cs & 0x04), blksize=BLOCK_SIZE)
        if cs & 0x02:
            t.indicated = _u32(data, 4)
            self._check_indicated(t)
        self._transfer = t
        return [bytes([0xA4]) + data[1:4] + bytes([BLOCK_SIZE, 0, 0, 0])]

    def _initiate_block_upload(self, data: bytes, now: float) -> list[bytes]:
        index, sub = _mux(data)
        blksize, pst = data[4], data[5]
        if not 1 <= blksize <= 127:
            raise SdoAbort(AbortCode.BLOCK_SIZE)
        value = self._dict.read(index, sub)
        if pst and len(value) <= pst:              # protocol switch: the plain upload
            return self._initiate_upload(bytes([0x40]) + data[1:4] + bytes(4), now)
        self._transfer = Transfer(Phase.BLOCK_UPLOAD_START, index, sub, now + self.timeout,
                                  data=bytearray(value), crc=bool(data[0] & 0x04),
                                  blksize=blksize)
        return [bytes([0xC6]) + data[1:4] + struct.pack("<I", len(value))]

    # -- transfers in progress -----------------------------------------------------------------

    def _continue(self, t: Transfer, data: bytes, now: float) -> list[bytes]:
        t.deadline = now + self.timeout
        step = {Phase.DOWNLOAD_SEGMENT: self._download_segment,
                Phase.UPLOAD_SEGMENT: self._upload_segment,
                Phase.BLOCK_DOWNLOAD: self._block_segment,
                Phase.BLOCK_DOWNLOAD_END: self._end_block_download,
                Phase.BLOCK_UPLOAD_START: self._start_block_upload,
                Phase.BLOCK_UPLOAD_ACK: self._block_upload_ack,
                Phase.BLOCK_UPLOAD_END: self._end_block_upload}[t.phase]
        return step(t, data)

    def _download_segment(self, t: Transfer, data: bytes) -> list[bytes]:
        cs = data[0]
        if cs >> 5 != 0:
            raise SdoAbort(AbortCode.COMMAND)
        toggle = (cs >> 4) & 1
        if toggle != t.toggle:
            raise SdoAbort(AbortCode.TOGGLE)
        t.data += data[1:8 - ((cs >> 1) & 0x07)]
        self._bound(t)
        answer = bytes([0x20 | (toggle << 4)]) + bytes(7)
        t.toggle ^= 1
        if cs & 0x01:                              # the last segment
            self._finish_download(t)
        return [answer]

    def _bound(self, t: Transfer) -> None:
        """Refuse data beyond what the client indicated or the object can take."""
        if t.indicated is not None and len(t.data) > t.indicated:
            raise SdoAbort(AbortCode.LENGTH)
        if t.fixed is not None and len(t.data) > t.fixed:
            raise SdoAbort(AbortCode.TOO_LONG)
        if len(t.data) > MAX_DOWNLOAD:
            raise SdoAbort(AbortCode.OUT_OF_MEMORY)

    def _finish_download(self, t: Transfer) -> None:
        """The client sent its last byte: compare with what it indicated, then store."""
        if t.indicated is not None and len(t.data) != t.indicated:
            raise SdoAbort(AbortCode.LENGTH)
        self._dict.write(t.index, t.subindex, bytes(t.data))
        self._transfer = None

    def _upload_segment(self, t: Transfer, data: bytes) -> list[bytes]:
        cs = data[0]
        if cs >> 5 != 3:
            raise SdoAbort(AbortCode.COMMAND)
        toggle = (cs >> 4) & 1
        if toggle != t.toggle:
            raise SdoAbort(AbortCode.TOGGLE)
        chunk, t.data = bytes(t.data[:7]), t.data[7:]
        last = not t.data
        t.toggle ^= 1
        if last:
            self._transfer = None
        head = (toggle << 4) | ((7 - len(chunk)) << 1) | int(last)
        return [bytes([head]) + chunk.ljust(7, b"\x00")]

    def _block_segment(self, t: Transfer, data: bytes) -> list[bytes]:
        seqno, last = data[0] & 0x7F, bool(data[0] & 0x80)
        if not 1 <= seqno <= t.blksize:
            raise SdoAbort(AbortCode.SEQUENCE)
        taken = seqno == t.seqno + 1
        if taken:                                  # in sequence; others wait for a resend
            t.seqno = seqno
            t.data += data[1:8]
            if t.fixed is None and len(t.data) > MAX_DOWNLOAD:
                raise SdoAbort(AbortCode.OUT_OF_MEMORY)
        if seqno < t.blksize and not last:
            return []
        answer = bytes([0xA2, t.seqno, BLOCK_SIZE]) + bytes(5)
        t.seqno = 0
        if last and taken:
            t.phase = Phase.BLOCK_DOWNLOAD_END
        return [answer]

    def _end_block_download(self, t: Transfer, data: bytes) -> list[bytes]:
        cs = data[0]
        if cs >> 5 != 6 or not cs & 0x01:
            raise SdoAbort(AbortCode.COMMAND)
        unused = (cs >> 2) & 0x07
        if unused:
            del t.data[-unused:]
        if t.crc and crc16(bytes(t.data)) != struct.unpack_from("<H", data, 1)[0]:
            raise SdoAbort(AbortCode.CRC)
        self._bound(t)
        self._finish_download(t)
        return [bytes([0xA1]) + bytes(7)]

    def _start_block_upload(self, t: Transfer, data: bytes) -> list[bytes]:
        if data[0] != 0xA3:
            raise SdoAbort(AbortCode.COMMAND)
        return self._send_block(t)

    def _segments(self, t: Transfer) -> int:
        """How many segments the whole value takes (one at least: an empty value is one
        segment of no data)."""
        return max(1, -(-len(t.data) // 7))

    def _send_block(self, t: Transfer) -> list[bytes]:
        """Send the next sub-block from the acknowledged offset."""
        first = t.offset // 7
        count = min(t.blksize, self._segments(t) - first)
        out = []
        for k in range(count):
            seg = first + k
            last = seg == self._segments(t) - 1
            chunk = bytes(t.data[7 * seg:7 * seg + 7]).ljust(7, b"\x00")
            out.append(bytes([(k + 1) | (0x80 if last else 0)]) + chunk)
        t.seqno = count
        t.phase = Phase.BLOCK_UPLOAD_ACK
        return out

    def _block_upload_ack(self, t: Transfer, data: bytes) -> list[bytes]:
        if data[0] != 0xA2:
            raise SdoAbort(AbortCode.COMMAND)
        ackseq, blksize = data[1], data[2]
        if ackseq > t.seqno:
            raise SdoAbort(AbortCode.SEQUENCE)
        if not 1 <= blksize <= 127:
            raise SdoAbort(AbortCode.BLOCK_SIZE)
        t.offset += 7 * ackseq
        t.blksize = blksize
        if t.offset < len(t.data) or (not t.data and ackseq == 0):
            return self._send_block(t)
        t.phase = Phase.BLOCK_UPLOAD_END
        unused = 7 * self._segments(t) - len(t.data)
        crc = crc16(bytes(t.data)) if t.crc else 0
        return [bytes([0xC1 | (unused << 2)]) + struct.pack("<H", crc) + bytes(5)]

    def _end_block_upload(self, t: Transfer, data: bytes) -> list[bytes]:
        if data[0] != 0xA1:
            raise SdoAbort(AbortCode.COMMAND)
        self._transfer = None
        return []


def _mux(data: bytes) -> tuple[int, int]:
    """Index and sub-index from bytes 1..3 of a request."""
    index, sub = struct.unpack_from("<HB", data, 1)
    return int(index), int(sub)


def _u32(data: bytes, offset: int) -> int:
    return int(struct.unpack_from("<I", data, offset)[0])
