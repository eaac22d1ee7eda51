"""qos - how chcos priorities and message kinds map onto Zenoh's priorities, express flag and
congestion control, and the checks of keys and priorities (see :mod:`chcos.comm.transport`).
"""

from __future__ import annotations

import zenoh

from chcos.comm.codec import EXPRESS_FROM, MAX_PRIORITY, MessageKind
from chcos.errors import LinkError

__all__ = ["EXPRESS_FROM", "PRIORITY_BANDS", "band_of", "check_key", "check_priority",
           "congestion_for", "is_express", "zenoh_priority"]

#: CHC-OS priority bands (lowest priority of the band, Zenoh priority), most urgent first.
PRIORITY_BANDS: tuple[tuple[int, zenoh.Priority], ...] = (
    (90, zenoh.Priority.REAL_TIME),
    (75, zenoh.Priority.INTERACTIVE_HIGH),
    (60, zenoh.Priority.INTERACTIVE_LOW),
    (45, zenoh.Priority.DATA_HIGH),
    (30, zenoh.Priority.DATA),
    (15, zenoh.Priority.DATA_LOW),
    (0, zenoh.Priority.BACKGROUND),
)
def check_priority(priority: int) -> int:
    """``priority`` if it is an integer 0..99. Raises LinkError otherwise."""
    if isinstance(priority, bool) or not isinstance(priority, int):
        raise LinkError(f"priority: expected an integer 0..{MAX_PRIORITY}, got {priority!r}")
    if not 0 <= priority <= MAX_PRIORITY:
        raise LinkError(f"priority: expected 0..{MAX_PRIORITY}, got {priority}")
    return priority


def band_of(priority: int) -> int:
    """The index in :data:`PRIORITY_BANDS` of ``priority``. Raises LinkError like above."""
    check_priority(priority)
    return next(i for i, (low, _) in enumerate(PRIORITY_BANDS) if priority >= low)


def zenoh_priority(priority: int) -> zenoh.Priority:
    """The Zenoh priority for CHC-OS ``priority`` 0..99 (see :data:`PRIORITY_BANDS`).

    Raises LinkError if ``priority`` is not an integer 0..99."""
    return PRIORITY_BANDS[band_of(priority)][1]


def is_express(priority: int) -> bool:
    """Whether messages of CHC-OS ``priority`` bypass batching. Raises LinkError like above."""
    return check_priority(priority) >= EXPRESS_FROM


def congestion_for(kind: MessageKind) -> zenoh.CongestionControl:
    """DROP for kinds a newer message supersedes (sensory, status), BLOCK for all others."""
    return zenoh.CongestionControl.DROP if kind.droppable else zenoh.CongestionControl.BLOCK


def check_key(what: str, key: str, *, concrete: bool) -> str:
    """``key`` if it is a valid Zenoh key expression (without wildcards if ``concrete``).
    Raises LinkError naming ``what`` otherwise."""
    if not isinstance(key, str) or not key:
        raise LinkError(f"{what}: expected a non-empty key string, got {key!r}")
    if concrete and ("*" in key or "$" in key):
        raise LinkError(f"{what}: expected a concrete key without wildcards, got {key!r}")
    try:
        zenoh.KeyExpr(key)
    except zenoh.ZError as exc:
        raise LinkError(f"{what}: {key!r} is not a valid Zenoh key expression: {exc}") from exc
    return key
