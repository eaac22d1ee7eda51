"""waits - what a task waiting on the message layer waits for, and how that wait ends.

A task blocked in ``read``, ``read_any``, ``wait_any``, ``invoke``/``done``, ``ask`` or
``read_exception`` records in its Tsktab entry the ports, links, tap or query it waits on, and
leaves :func:`forget` (or, waiting on input ports only, :func:`forget_ports`) as its ``unwait``:
the kernel calls it when it wakes or cancels the task, without knowing what any of those are.
"""

from __future__ import annotations

from chcos.tables.tasks import TaskEntry


def forget(t: TaskEntry) -> None:
    """End every message-layer wait of ``t``: it waits on no input port, its tap names it as
    its waiter no more, and it waits for no link, command or query (an
    :data:`chcos.tables.tasks.Unwait`)."""
    t.wait_ports = ()
    t.wait_link = None
    t.wait_query = None
    tap = t.tap
    if tap is not None and tap.waiter is t:
        tap.waiter = None
    if t.multi_wait:
        t.multi_wait = False
        t.wait_links = ()
        t.wait_commands = False
        t.wake_filter = None


def forget_ports(t: TaskEntry) -> None:
    """End a wait of ``t`` on input ports only (``read``, ``read_any``): it waits on no port
    any more, so a message there no longer wakes it (an :data:`chcos.tables.tasks.Unwait`)."""
    t.wait_ports = ()
