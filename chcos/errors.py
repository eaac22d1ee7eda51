"""errors - the one exception root of chcos and its children, one per OS layer.

Every error names what it is about (file and key, task, link, device) and chains its cause with
``raise ... from``. Catch :class:`ChcosError` to catch everything chcos raises on purpose.
"""

from __future__ import annotations


class ChcosError(Exception):
    """Root of every error chcos raises on purpose."""


class KernelError(ChcosError):
    """The kernel was misused: a task stepped outside the kernel, a bad trap, a stopped kernel."""


class HandlerError(KernelError):
    """An interrupt handler or a timer callback failed on the kernel thread. The kernel logged it
    and kept running; :meth:`chcos.kernel.scheduler.Kernel.check` raises it (the failure chained
    as the cause) so that it is not only collected."""


class TaskError(ChcosError):
    """A task-manager call failed: unknown task id, illegal state change."""


class MessageError(ChcosError):
    """A message-manager call failed: no such port or link, wrong link type for the call."""


class QueueOverflow(MessageError):
    """A queued link was full: the message was refused and the sender told (never lost silently)."""


class Busy(MessageError):
    """``invoke(..., wait=False)`` found the target owned at an equal or higher priority."""


class Preempted(ChcosError):
    """Raised inside a task activation that lost its owner to a higher-priority command.

    The kernel throws it into the running activation so the task can clean up; if the task lets it
    propagate, the activation ends quietly (this is not an abnormal completion).
    """


class ReadTimeout(MessageError):
    """A blocking read with a timeout saw no message in time."""


class SensorFailure(ChcosError):
    """A sensor a task reads is failed or stale; the appendix-2 "sensor failure" condition."""

    def __init__(self, device: str, reason: str) -> None:
        super().__init__(f"sensor failure on {device}: {reason}")
        self.device = device
        self.reason = reason


class DeviceError(ChcosError):
    """A device-manager call failed: unknown device, write to a sensor, value outside limits."""


class ConfigError(ChcosError):
    """A device map or system file is invalid. The message names the file, the key path or line,
    and what was expected; an invalid file is rejected whole."""


class BusError(ChcosError):
    """A field bus could not be opened or used (the OS or library error is chained as the cause)."""


class DriverNotAvailable(BusError):
    """A bus kind names a driver whose module cannot be imported or is not registered."""


class InstallError(ChcosError):
    """An install, setpri or invoke was refused by the system manager; tables are unchanged."""


class CommandSyntaxError(InstallError):
    """A host command line (``install -m0i2o1 ...``) could not be parsed."""


class LinkError(ChcosError):
    """The communications link between host and satellites failed or refused a request."""
