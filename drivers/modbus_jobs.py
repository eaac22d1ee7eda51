"""modbus_jobs - the typed keys of the Modbus drivers' paced jobs (the ``what`` of a
:attr:`drivers.jobs.JobOp.POLL` job): the polls of the sensors, one per poll period, and the
link's own chores (the liveness probe, the watchdog write, the read-back of write-failed
actuators). The driver's worker dispatches on them with ``match``
(:meth:`drivers.modbus_link.ModbusDriver._run`); a write job carries a
:class:`drivers.modbus_requests.QueuedWrite`.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass


@dataclass(frozen=True)
class SensorPoll:
    """Read the sensors polled every ``period`` seconds (one plan of reads)."""

    period: float


class LinkChore(enum.Enum):
    """The driver's paced jobs beside the sensor polls."""

    #: a request to the units no poll reads (their actuators only), so a lost link is noticed
    PROBE = "probe"
    #: the next value of the bus's watchdog register
    WATCHDOG = "watchdog"
    #: read each write-failed actuator back: an answer ends its write failure
    READBACK = "readback"


#: What a Modbus poll job is about.
ModbusPoll = SensorPoll | LinkChore
