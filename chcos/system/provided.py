"""provided - the drivers chcos provides itself (thesis 6.1.5, tasks A3 and A4).

:func:`file_sampler` samples a file at the rate set when the system is downloaded (install
parameter ``rate``, A3 'testfile'): each sample is the file's next line, sent upward (numbers
become floats, other lines stay text); the file is read again whenever it changes, so edits reach
the hierarchy at the next sample. :func:`terminal_log` connects a terminal and an output log (A4):
every line typed on the terminal goes up as a sensory message - from a real terminal (a tty or
pty device named as its input, read on a thread of its own) or from the host (``inject /dev/tty0
text``) - and the log gets the lines, the commands A4 receives and the pertinent system events
(installs, priority changes, invocations, completions, failures, pre-emptions, restarts,
suspensions, e-stops), one line each with the time.
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import stat
import threading
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import Any

from chcos.errors import MessageError, ReadTimeout
from chcos.user.context import EventKind, TaskContext

_log = logging.getLogger("chcos.system.provided")


def _value(line: str) -> Any:
    text = line.strip()
    try:
        return float(text)
    except ValueError:
        return text


def _stop(command: Any) -> bool:
    return isinstance(command, dict) and command.get("op") in ("shutdown", "stop")


class _Sampled:
    """The samples of one file, read again when the file changes (size, time or inode)."""

    def __init__(self, name: str, path: str) -> None:
        self.name = name
        self.path = path
        self.key: tuple[int, int, int] | None = None
        self.lines: list[str] = []

    def current(self) -> list[str]:
        """The file's samples now. Raises MessageError if it cannot be read or is empty."""
        try:
            st = os.stat(self.path)
            key = (st.st_mtime_ns, st.st_size, st.st_ino)
            if key != self.key:
                text = Path(self.path).read_text(encoding="utf-8")
                self.lines = [ln for ln in text.splitlines()
                              if ln.strip() and not ln.startswith("#")]
                self.key = key
        except (OSError, UnicodeDecodeError) as exc:
            raise MessageError(f"{self.name}: cannot read {self.path}: {exc}") from exc
        if not self.lines:
            raise MessageError(f"{self.name}: {self.path} has no samples")
        return self.lines


async def file_sampler(ctx: TaskContext, command: Any) -> int:
    """Send one line of the file on input port 0 upward every ``1/rate`` seconds (install
    parameter ``rate``, set when the system is downloaded; a command may override it; default
    10 Hz), in order, starting again at the end of the file unless ``loop`` is false (it then
    completes with the number of samples sent). An edit of the file is seen at the next sample.
    A newer command from the owner is taken at once; ``{"op": "shutdown"}`` (or ``stop``) ends
    the activation with the number of samples sent.

    Raises MessageError if input 0 is not a file, the file cannot be read or has no samples, or
    the rate is not a positive number.
    """
    opts = dict(ctx.params)
    if isinstance(command, dict):
        opts.update(command)
    rate = float(opts.get("rate", 10.0))
    loop = bool(opts.get("loop", True))
    if not rate > 0 or rate == float("inf"):
        raise MessageError(f"{ctx.name}: rate must be a positive number of samples a second, "
                           f"got {rate}")
    if _stop(command):
        return 0
    source = _Sampled(ctx.name, ctx.input_file(0))
    source.current()
    period = 1.0 / rate
    sent = 0
    index = 0
    next_at = ctx.now + period
    while True:
        try:
            ev = await ctx.wait_any(commands=True, timeout=max(0.0, next_at - ctx.now))
        except ReadTimeout:
            lines = source.current()
            if index >= len(lines):  # the end (or the file got shorter)
                if not loop:
                    return sent
                index = 0
            ctx.put(_value(lines[index]))
            ctx.world.sensory.update(sample=lines[index], line=index + 1)
            index += 1
            sent += 1
            next_at += period
            continue
        if _stop(ev.value):
            return sent
        if isinstance(ev.value, dict) and "rate" in ev.value:
            rate = float(ev.value["rate"])
            if not rate > 0 or rate == float("inf"):
                raise MessageError(f"{ctx.name}: rate must be a positive number, got {rate}")
            period = 1.0 / rate
            next_at = ctx.now + period


file_sampler.chcos_system_driver = True  # type: ignore[attr-defined]

#: The system events the terminal/log driver writes to its log.
LOGGED_EVENTS = frozenset({
    "install", "boot", "reload", "setpri", "resetpri", "invoke", "complete", "abnormal",
    "preempt", "release", "restart", "restart-waiting", "standing", "suspend", "resume", "reset",
    "close", "estop", "device-failed", "device-stale", "device-ok", "device-suspended"})


class _TerminalReader:
    """Reads lines from a terminal device on a thread and feeds them to input port 0."""

    def __init__(self, ctx: TaskContext, path: str) -> None:
        self.ctx = ctx
        self.path = path
        self.stopping = threading.Event()
        self.fd = os.open(path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
        self.thread = threading.Thread(target=self._run, name=f"chcos-tty-{ctx.name}",
                                       daemon=True)
        self.thread.start()

    def _run(self) -> None:
        buf = b""
        while not self.stopping.is_set():
            try:
                ready, _, _ = select.select([self.fd], [], [], 0.1)
                if not ready:
                    continue
                chunk = os.read(self.fd, 4096)
            except OSError:  # the terminal went away (EIO when the other end closed)
                return
            if not chunk:
                continue
            buf += chunk.replace(b"\r", b"\n")
            *lines, buf = buf.split(b"\n")
            for raw in lines:
                line = raw.decode("utf-8", "replace").strip()
                if line:
                    self.ctx.feed(0, line)

    def close(self) -> None:
        """Stop the thread and close the terminal."""
        self.stopping.set()
        self.thread.join(timeout=2.0)
        with contextlib.suppress(OSError):
            os.close(self.fd)


def _is_terminal(path: str) -> bool:
    try:
        return stat.S_ISCHR(os.stat(path).st_mode) and path.startswith(("/dev/pts/", "/dev/tty"))
    except OSError:
        return False


_ATTACHED: weakref.WeakKeyDictionary[TaskContext, tuple[_TerminalReader | None,
                                                         Callable[[], None]]] = \
    weakref.WeakKeyDictionary()
"""The terminal reader and event watch of each terminal/log task: they belong to the task, not to
one activation, so nothing typed or logged is lost while a new owner's command restarts it."""


def _detach(ctx: TaskContext) -> None:
    reader, unwatch = _ATTACHED.pop(ctx, (None, lambda: None))
    unwatch()
    if reader is not None:
        reader.close()


async def terminal_log(ctx: TaskContext, command: Any) -> None:
    """Pass terminal lines (input port 0) upward and keep the log on output port 0: the lines,
    the commands received (the first and every newer one of the owner) and the system events of
    :data:`LOGGED_EVENTS`. The terminal is read on a thread when it is a real terminal device
    (install parameter ``tty=inject`` keeps to the host's ``inject``); the reader and the event
    watch stay attached across activations and are let go when the activation is closed (system
    shutdown, reload) or told ``{"op": "shutdown"}``. Runs until pre-empted or released."""

    def log(text: str) -> None:
        try:
            ctx.write(0, f"{ctx.now:.3f} {text}")
        except MessageError as exc:  # the log link is suspended or the file unwritable
            ctx.world.sensory["log_errors"] = ctx.world.sensory.get("log_errors", 0) + 1
            _log.warning("%s: log line lost: %s", ctx.name, exc)

    def on_event(kind: str, detail: str) -> None:
        if kind in LOGGED_EVENTS:
            log(f"event {kind}: {detail}")

    if command is not None:
        log(f"command {command}")
    if _stop(command):
        _detach(ctx)
        return
    if ctx not in _ATTACHED:
        tty = ctx.inputs[0] if ctx.inputs else ""
        reader = (_TerminalReader(ctx, tty)
                  if ctx.params.get("tty") != "inject" and _is_terminal(tty) else None)
        _ATTACHED[ctx] = (reader, ctx.watch_events(on_event))
    try:
        while True:
            ev = await ctx.wait_any([0], commands=True)
            if ev.kind is EventKind.COMMAND:
                log(f"command {ev.value}")
                if _stop(ev.value):
                    _detach(ctx)
                    return
            elif ev.kind is EventKind.MESSAGE:
                log(f"tty {ev.value}")
                ctx.put(ev.value)
    except GeneratorExit:  # closed for good (shutdown, reload): let the terminal go
        _detach(ctx)
        raise


terminal_log.chcos_system_driver = True  # type: ignore[attr-defined]
