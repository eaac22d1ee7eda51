"""sysdrivers - the drivers chcos provides itself (thesis 6.1.5, tasks A3 and A4).

:func:`file_sampler` samples a file at a set rate into the hierarchy (A3 'testfile'): each line is
one sensory message upward (numbers become floats, other lines stay text). :func:`terminal_log`
connects a terminal and an output log (A4): every line typed on the terminal (``inject /dev/tty0
text`` from the host, or the console of ``chcos run --tty``) goes up as a sensory message, and
every command it receives is written to the log with the time.
"""

from __future__ import annotations

from typing import Any

from chcos.errors import MessageError
from chcos.usrmgr import TaskContext


def _value(line: str) -> Any:
    text = line.strip()
    try:
        return float(text)
    except ValueError:
        return text


async def file_sampler(ctx: TaskContext, command: Any) -> int:
    """Send the lines of the file on input port 0 upward, ``rate`` lines a second (install
    parameter or command key ``rate``, default 10 Hz); start again at the end of the file unless
    ``loop`` is false, in which case it completes with the number of lines sent.

    Raises MessageError if input 0 is not a file or the file cannot be read.
    """
    opts = dict(ctx.params)
    if isinstance(command, dict):
        opts.update(command)
    rate = float(opts.get("rate", 10.0))
    loop = bool(opts.get("loop", True))
    if rate <= 0:
        raise MessageError(f"{ctx.name}: rate must be positive, got {rate}")
    path = ctx.input_file(0)
    try:
        with open(path, encoding="utf-8") as fh:
            lines = [ln for ln in fh.read().splitlines() if ln.strip() and not ln.startswith("#")]
    except OSError as exc:
        raise MessageError(f"{ctx.name}: cannot read {path}: {exc}") from exc
    if not lines:
        raise MessageError(f"{ctx.name}: {path} has no samples")
    period = 1.0 / rate
    sent = 0
    next_at = ctx.now
    while True:
        for line in lines:
            next_at += period
            await ctx.sleep(max(0.0, next_at - ctx.now))
            ctx.put(_value(line))
            sent += 1
        if not loop:
            return sent


file_sampler.chcos_system_driver = True  # type: ignore[attr-defined]


async def terminal_log(ctx: TaskContext, command: Any) -> None:
    """Pass terminal lines (input port 0) upward and log commands and lines to the file on
    output port 0. Runs until pre-empted or released."""
    if command is not None:
        ctx.write(0, f"{ctx.now:.3f} command {command}")
    while True:
        line = await ctx.read(0)
        ctx.write(0, f"{ctx.now:.3f} tty {line}")
        ctx.put(line)


terminal_log.chcos_system_driver = True  # type: ignore[attr-defined]
