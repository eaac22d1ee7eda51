"""transactions - the sans-IO matching of Modbus answers to requests, for both framings.

A :class:`Request` is a request PDU (encoded by pymodbus' PDU classes) and the unit it goes
to; what comes back is an :data:`Outcome`: an :class:`Answer` (the response PDU, checked to be
the answer of exactly that request), a :class:`Refused` (an exception answer and its code), an
:class:`Unusable` answer (something came back, and it is not that answer: a bad CRC, junk or a
truncated frame, the wrong function code, a byte count other than the request's, another unit,
a write that does not echo the request - each a :class:`Cause`) or :class:`NoAnswer`.

Matching uses everything the framing carries:

* Modbus TCP (:class:`TcpStream`, :func:`match_tcp`): the MBAP header's transaction id (an
  answer to an earlier request that timed out is :attr:`Cause.LATE`, skipped while the answer
  of this one is still awaited), protocol id 0, unit, function, byte count;
* Modbus RTU (:class:`RtuExchange`): unit, function, byte count and CRC of a frame whose length
  the request fixes; a whole frame of another unit (a late answer) is skipped, and bytes that
  arrive before the request could have been answered are no answer to it. The transports
  flush the input before each request, so nothing read after a timeout is kept.

No I/O: the transports (:mod:`drivers.modbus.transport`) move the bytes, this module says what
they are. Costs: a request's bytes are built once per planned read (:func:`read_request`).
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

from pymodbus.pdu.bit_message import (
    ReadCoilsRequest,
    ReadCoilsResponse,
    ReadDiscreteInputsRequest,
    WriteMultipleCoilsRequest,
    WriteSingleCoilRequest,
)
from pymodbus.pdu.pdu import ModbusPDU
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadHoldingRegistersResponse,
    ReadInputRegistersRequest,
    WriteMultipleRegistersRequest,
    WriteSingleRegisterRequest,
)

from drivers.codecs.modbus import (
    BIT_TABLES,
    BROADCAST,
    classify_rtu_answer,
    crc16,
    rtu_answer_size,
    with_crc,
)

_READS: dict[str, type[ModbusPDU]] = {
    "coil": ReadCoilsRequest, "discrete": ReadDiscreteInputsRequest,
    "holding": ReadHoldingRegistersRequest, "input": ReadInputRegistersRequest}
_MBAP = struct.Struct(">HHHB")
MBAP_BYTES = 7
#: The longest PDU an ADU carries (the serial line's 256-byte ADU less unit and CRC).
MAX_PDU = 253


class Cause(enum.StrEnum):
    """Why something that came back is not the answer of the request (an error class of the
    bus statistics)."""

    TIMEOUT = "timeout"           # nothing came back in time
    CRC = "crc"                   # RTU: a frame of the request's unit and function, bad CRC
    FRAMING = "framing"           # truncated, junk, a MBAP length that does not fit
    FUNCTION = "function"         # another function code than the request's
    COUNT = "count"               # a byte count other than the request asked for
    UNIT = "unit"                 # TCP: the answer names another unit
    TRANSACTION = "transaction"   # TCP: a transaction id no request of ours had
    LATE = "late"                 # the answer of an earlier request, after its timeout
    ECHO = "echo"                 # a write answer that does not repeat the request
    PROTOCOL = "protocol"         # TCP: a protocol id other than 0 (not Modbus)


@dataclass(frozen=True, slots=True)
class Request:
    """One request: its unit and PDU (function code first), what it is about (for reasons),
    and for a read the byte count of its answer's data (-1: a write, answered by an echo)."""

    unit: int
    pdu: bytes
    what: str
    byte_count: int = -1

    @property
    def function(self) -> int:
        """The function code."""
        return self.pdu[0]

    @property
    def broadcast(self) -> bool:
        """Unit 0: carried out by every slave, answered by none."""
        return self.unit == BROADCAST

    def rtu_frame(self) -> bytes:
        """The request as it goes on an RTU line: unit, PDU, CRC."""
        return with_crc(bytes([self.unit]) + self.pdu)

    def tcp_adu(self, tid: int) -> bytes:
        """The request as it goes on a Modbus TCP connection with transaction id ``tid``."""
        return _MBAP.pack(tid, 0, len(self.pdu) + 1, self.unit) + self.pdu

    def rtu_answer_bytes(self) -> int:
        """The length of the RTU frame of its (non-exception) answer."""
        return 1 + (2 + self.byte_count if self.byte_count >= 0 else 5) + 2


def _pdu(message: ModbusPDU) -> bytes:
    return bytes([message.function_code]) + message.encode()


def read_request(unit: int, table: str, address: int, count: int, what: str) -> Request:
    """The read of ``count`` entries of ``table`` from ``address`` (function 1, 2, 3 or 4).
    Raises ValueError for a count or address the protocol does not carry."""
    pdu = _pdu(_READS[table](address=address, count=count, dev_id=unit))
    data = (count + 7) // 8 if table in BIT_TABLES else 2 * count
    return Request(unit, pdu, what, data)


def write_request(unit: int, table: str, address: int, registers: list[int] | None = None,
                  bit: bool | None = None, what: str = "") -> Request:
    """The write of one coil (function 5), one register (6) or several registers (16)."""
    message: ModbusPDU
    if table == "coil":
        message = WriteSingleCoilRequest(address=address, bits=[bool(bit)], dev_id=unit)
    elif registers is not None and len(registers) == 1:
        message = WriteSingleRegisterRequest(address=address, registers=registers, dev_id=unit)
    else:
        message = WriteMultipleRegistersRequest(address=address, registers=registers or [],
                                                dev_id=unit)
    return Request(unit, _pdu(message), what)


def write_bits_request(unit: int, address: int, bits: list[bool], what: str) -> Request:
    """The write of several coils (function 15)."""
    return Request(unit, _pdu(WriteMultipleCoilsRequest(address=address, bits=bits,
                                                         dev_id=unit)), what)


# ---- outcomes ----------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Answer:
    """The answer of the request: its response PDU (function code first)."""

    pdu: bytes


@dataclass(frozen=True, slots=True)
class Refused:
    """An exception answer: the device answered and refused, with ``code``."""

    code: int


@dataclass(frozen=True, slots=True)
class Unusable:
    """Something came back that is not the request's answer, for ``cause``."""

    cause: Cause
    detail: str


@dataclass(frozen=True, slots=True)
class NoAnswer:
    """Nothing came back within the timeout."""

    detail: str = "no response"


Outcome = Answer | Refused | Unusable | NoAnswer


def check_pdu(req: Request, pdu: bytes) -> Outcome:
    """What the response PDU ``pdu`` (of the request's unit) is for ``req``: the answer, an
    exception answer, or unusable for its function code, byte count or echo."""
    if not pdu:
        return Unusable(Cause.FRAMING, "an empty answer")
    fc = pdu[0]
    if fc == req.function | 0x80:
        if len(pdu) != 2:
            return Unusable(Cause.FRAMING, f"exception answer {pdu.hex()} of {len(pdu)} bytes, "
                                           f"expected 2")
        return Refused(pdu[1])
    if fc != req.function:
        return Unusable(Cause.FUNCTION, f"answer with function code {fc} to a request with "
                                        f"function code {req.function}: {pdu[:16].hex()}")
    if req.byte_count >= 0:
        count = pdu[1] if len(pdu) > 1 else -1
        if count != req.byte_count:
            return Unusable(Cause.COUNT, f"answer of {count} data bytes to a request for "
                                         f"{req.byte_count}: {pdu[:16].hex()}")
        if len(pdu) != 2 + count:
            return Unusable(Cause.FRAMING, f"answer of {len(pdu) - 2} data bytes with byte "
                                           f"count {count}")
        return Answer(pdu)
    expected = req.pdu if req.function in (5, 6) else req.pdu[:5]
    if pdu != expected:
        return Unusable(Cause.ECHO, f"write answer {pdu.hex()} does not repeat the request "
                                    f"{expected.hex()}")
    return Answer(pdu)


def registers_of(answer: Answer) -> list[int]:
    """The registers of a checked read answer (function 3 or 4)."""
    response = ReadHoldingRegistersResponse()
    response.decode(answer.pdu[1:])
    return list(response.registers)


def bits_of(answer: Answer, count: int) -> list[bool]:
    """The first ``count`` bits of a checked read answer (function 1 or 2)."""
    response = ReadCoilsResponse()
    response.decode(answer.pdu[1:])
    return list(response.bits[:count])


# ---- Modbus TCP --------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class TcpFrame:
    """One Modbus TCP frame: MBAP header fields and the PDU."""

    tid: int
    protocol: int
    unit: int
    pdu: bytes


class TcpStream:
    """The frames of one TCP connection's byte stream, each delimited by its MBAP length.
    :meth:`feed` takes the bytes as they come; a length that no Modbus frame has means the
    stream cannot be followed any more (:attr:`broken` is set with the reason: a
    connection-level cause)."""

    def __init__(self) -> None:
        self._buf = bytearray()
        #: why the stream cannot be followed ("" while it can)
        self.broken = ""

    def feed(self, data: bytes) -> list[TcpFrame]:
        """The whole frames ``data`` completes, in order."""
        buf = self._buf
        buf += data
        out: list[TcpFrame] = []
        while len(buf) >= MBAP_BYTES and not self.broken:
            tid, protocol, length, unit = _MBAP.unpack_from(buf)
            if not 2 <= length <= MAX_PDU + 1:
                self.broken = (f"a MBAP header with length {length} ({bytes(buf[:7]).hex()}): "
                               f"not a Modbus TCP frame")
                break
            end = 6 + length
            if len(buf) < end:
                break
            out.append(TcpFrame(tid, protocol, unit, bytes(buf[MBAP_BYTES:end])))
            del buf[:end]
        return out

    def clear(self) -> None:
        """Forget every byte not yet taken (a new connection)."""
        self._buf.clear()
        self.broken = ""


def match_tcp(req: Request, tid: int, frame: TcpFrame, late: set[int]) -> Outcome | None:
    """What ``frame`` is for ``req`` sent with transaction id ``tid``: its outcome, or None for
    the answer of an earlier request in ``late`` (timed out: skipped, the caller counts it)."""
    if frame.tid != tid:
        if frame.tid in late:
            late.discard(frame.tid)
            return None
        return Unusable(Cause.TRANSACTION, f"answer with transaction id {frame.tid} to the "
                                           f"request with {tid}")
    if frame.protocol != 0:
        return Unusable(Cause.PROTOCOL, f"answer with protocol id {frame.protocol} (Modbus: 0)")
    if frame.unit != req.unit:
        return Unusable(Cause.UNIT, f"answer from unit {frame.unit} to a request to unit "
                                    f"{req.unit}")
    return check_pdu(req, frame.pdu)


# ---- Modbus RTU --------------------------------------------------------------------------------
class RtuExchange:
    """The answer of one RTU request, from the bytes the line delivers after the request was
    sent (:meth:`feed`), or from what came by the timeout (:meth:`timed_out`). A whole frame of
    another unit with a good CRC is skipped (counted in :attr:`skipped`: a late answer or
    another master's traffic); anything else is judged as the answer."""

    def __init__(self, req: Request) -> None:
        self.req = req
        self.frame = req.rtu_frame()
        self._buf = bytearray()
        #: frames of other units skipped
        self.skipped = 0

    def feed(self, data: bytes) -> Outcome | None:
        """The outcome once ``data`` (appended to what came before) decides it; None while the
        answer is incomplete."""
        buf = self._buf
        buf += data
        unit = self.req.unit
        while buf:
            size = rtu_answer_size(bytes(buf[:3]))
            if size is None:
                if len(buf) < 3:
                    return None
                return self._unusable()           # no answer starts like this: junk
            if len(buf) < size:
                return None
            frame = bytes(buf[:size])
            good = crc16(frame[:-2]).to_bytes(2, "big") == frame[-2:]
            if frame[0] != unit:
                if not good:
                    return self._unusable()
                self.skipped += 1                 # another unit's frame: not ours
                del buf[:size]
                continue
            if not good:
                return self._unusable()
            return check_pdu(self.req, frame[1:-2])
        return None

    def timed_out(self) -> Outcome:
        """The outcome at the timeout: nothing (no answer), or what the bytes that came are."""
        if not self._buf:
            return NoAnswer("no response (silence)")
        return self._unusable()

    def _unusable(self) -> Unusable:
        kind, why = classify_rtu_answer(self.frame, bytes(self._buf))
        return Unusable(Cause(kind), why)

    @property
    def received(self) -> bytes:
        """The bytes taken so far (skipped frames excluded)."""
        return bytes(self._buf)
