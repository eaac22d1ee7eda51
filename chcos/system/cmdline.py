"""cmdline - the host's command syntax, as in thesis section 6.3, plus ordinary long options.

``install [-m#i#o#[s]] tsk infile... outfile...`` (also ``-m0 -i2 -o1`` and ``--machine 0 --inputs 2
--outputs 1``; ``s``, ``-s`` or ``--standing`` for a standing task, ``--restart=never|on-recovery|
always`` and ``--backoff=S`` for its restart policy; ``install -m1 sysfile`` loads a satellite, a
second time reloads it), ``setpri -# srctsk dsttsk``, ``resetpri tsk`` / ``resetpri srctsk
dsttsk``, ``invoke [-#] tsk [key=value...]``, plus ``suspend``, ``resume``, ``close``, ``reset``,
``inject``, ``axis`` (the commands of a CiA 402 axis), ``nmt`` (an NMT command to a CANopen
node) and ``map``.
Parsing is pure: it returns a request record and raises CommandSyntaxError naming the command,
the word and what was expected.
"""

from __future__ import annotations

import json
import math
import re
import shlex
from dataclasses import dataclass, field
from typing import Any

from chcos.devices.spec import MAX_MACHINE
from chcos.errors import CommandSyntaxError
from chcos.helpers import NAME_PATTERN
from chcos.tables.messages import PRIORITIES

MAX_LINE = 16384        # characters in one host command line (longer lines are refused unparsed)
MAX_NAME = 128          # characters in a task name
MAX_CODE = 1024         # characters in a task's code reference (a file path or module:function)
MAX_FILE_PART = 255     # characters in one part of a code file's path (the file system's limit)

_MODULE_PART = re.compile(r"[A-Za-z0-9_-]+")
_COMBINED = re.compile(r"^-(?:m(\d+))?(?:i(\d+))?(?:o(\d+))?(s)?$")
_PRIO = re.compile(r"^-(\d+)$")


@dataclass(frozen=True)
class Install:
    """An install request: task ``name`` with code ``code`` on ``machine``."""

    name: str
    machine: int
    inputs: tuple[str, ...] = ()
    outputs: tuple[str, ...] = ()
    code: str = ""
    role: str = "task"
    level: int | None = None
    params: dict[str, Any] = field(default_factory=dict)
    queued: dict[str, int] = field(default_factory=dict)
    standing: bool = False  # always on: started at install/boot, re-armed when released
    restart: str = "never"  # after an abnormal end: never, on-recovery, always
    backoff: float = 1.0  # seconds before a restart


#: Restart policies of ``install --restart=``: the thesis' default is ``never`` (the owner decides).
RESTART_POLICIES = ("never", "on-recovery", "always")


@dataclass(frozen=True)
class Boot:
    """``install -mN sysfile``: (re)load satellite ``machine`` from the system file."""

    machine: int
    sysfile: str


@dataclass(frozen=True)
class SetPri:
    """Set the priority of the link ``src``/``dst``."""

    priority: int
    src: str
    dst: str


@dataclass(frozen=True)
class ResetPri:
    """``resetpri SRC DST``: the link ``src``/``dst`` back to its default priority."""

    src: str
    dst: str


@dataclass(frozen=True)
class Invoke:
    """Send a command message from the host to ``task``."""

    task: str
    command: dict[str, Any] = field(default_factory=dict)
    priority: int | None = None


@dataclass(frozen=True)
class TaskOp:
    """``suspend``/``resume``/``close`` a task from the host."""

    op: str
    task: str


@dataclass(frozen=True)
class Inject:
    """Feed a reading to a sensor (or a line to a terminal device) from the host."""

    device: str
    value: Any


@dataclass(frozen=True)
class ShowMap:
    """Print the system map."""


#: ``axis NAME WORD``: the operator's commands of a CiA 402 axis (``status`` when no word)
AXIS_WORDS = ("status", "enable", "disable", "quick-stop", "fault-reset", "safe-stop",
              "set-mode", "home")


@dataclass(frozen=True)
class AxisCmd:
    """``axis NAME [WORD [MODE]]``: command CiA 402 axis ``device`` (``word``, one of
    :data:`AXIS_WORDS`; ``mode`` only for set-mode: a mode name or number, "" for the map's),
    or show what its drive last confirmed."""

    device: str
    word: str = "status"
    mode: str = ""


#: ``nmt WORD NODE [BUS]``: the NMT commands of CiA 301 (7.2.8.3.1), as the host words them
NMT_WORDS = ("start", "stop", "preop", "reset", "reset-comm")


@dataclass(frozen=True)
class NmtCmd:
    """``nmt WORD NODE [BUS]``: send NMT command ``word`` (one of :data:`NMT_WORDS`) to
    CANopen node ``node`` (1..127) of bus ``bus`` ("": the one CANopen bus that has it)."""

    word: str
    node: int
    bus: str = ""


Request = (Install | Boot | SetPri | ResetPri | Invoke | TaskOp | Inject | ShowMap | AxisCmd
           | NmtCmd)


def _int(cmd: str, word: str, what: str, lo: int = 0, hi: int | None = None) -> int:
    try:
        n = int(word)
    except ValueError:
        raise CommandSyntaxError(f"{cmd}: {what} {word!r} is not a whole number") from None
    if n < lo or (hi is not None and n > hi):
        rng = f"{lo}..{hi}" if hi is not None else f">= {lo}"
        raise CommandSyntaxError(f"{cmd}: {what} {n} is out of range ({rng})")
    return n


MAX_DEPTH = 16          # nesting of lists/objects in a command-line value
_NON_FINITE = frozenset({"nan", "inf", "infinity"})


def _bad_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number")


def _check_json(cmd: str, word: str, v: Any, depth: int = 0) -> None:
    if depth > MAX_DEPTH:
        raise CommandSyntaxError(f"{cmd}: value {_short(word)} is nested more than {MAX_DEPTH} "
                                 f"levels deep; expected a flatter value")
    if isinstance(v, float) and not math.isfinite(v):
        raise CommandSyntaxError(f"{cmd}: value {_short(word)} is out of range; expected a "
                                 f"finite number")
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) > 2**63 - 1:
        raise CommandSyntaxError(f"{cmd}: value {_short(word)} is out of range; expected an "
                                 f"integer of magnitude < 2**63")
    items = v.values() if isinstance(v, dict) else v if isinstance(v, list) else ()
    for item in items:
        _check_json(cmd, word, item, depth + 1)


def _short(text: str, limit: int = 40) -> str:
    return repr(text if len(text) <= limit else text[:limit - 3] + "...")


def parse_value(text: str, cmd: str = "value", numbers_only_finite: bool = False) -> Any:
    """A command-line value: JSON if it parses (numbers, true, lists...), else the string.

    Raises CommandSyntaxError (naming ``cmd``) for JSON's NaN/Infinity, numbers that overflow
    (``1e400``), integers of 2**63 and more, and values nested more than MAX_DEPTH levels; with
    ``numbers_only_finite`` also for words that ``float()`` would read as nan or an infinity
    (``nan``, ``-inf``...), so that they never reach a task as a number."""
    if numbers_only_finite and text.strip().lower().lstrip("+-") in _NON_FINITE:
        raise CommandSyntaxError(f"{cmd}: value {_short(text)} is not a finite number; expected "
                                 f"a finite number or a word that is not one")
    try:
        v = json.loads(text, parse_constant=_bad_constant)
    except RecursionError:
        raise CommandSyntaxError(f"{cmd}: value {_short(text)} is nested too deeply; expected "
                                 f"at most {MAX_DEPTH} levels") from None
    except ValueError as exc:
        if "is not a number" in str(exc):
            raise CommandSyntaxError(f"{cmd}: value {_short(text)} is not a finite number "
                                     f"({exc}); expected a finite number") from None
        return text
    _check_json(cmd, text, v)
    return v


def _kv(cmd: str, word: str) -> tuple[str, str]:
    key, eq, value = word.partition("=")
    if not eq or not key:
        raise CommandSyntaxError(f"{cmd}: expected key=value, got {word!r}")
    return key, value


def _install(args: list[str]) -> Install | Boot:
    machine: int | None = None
    n_in: int | None = None
    n_out: int | None = None
    code = ""
    role = "task"
    level: int | None = None
    params: dict[str, Any] = {}
    queued: dict[str, int] = {}
    standing = False
    restart = "never"
    backoff = 1.0
    rest: list[str] = []
    it = iter(args)
    for word in it:
        if word in ("-s", "--standing"):
            standing = True
            continue
        m = _COMBINED.match(word)
        if m and word != "-":
            if m.group(4) is not None:
                standing = True
            if m.group(1) is not None:
                machine = _int("install", m.group(1), "machine number", 0, MAX_MACHINE)
            if m.group(2) is not None:
                n_in = _int("install", m.group(2), "input count", 0, 8)
            if m.group(3) is not None:
                n_out = _int("install", m.group(3), "output count", 0, 8)
            continue
        if word.startswith("--"):
            opt, eq, val = word.partition("=")
            if not eq:
                val = next(it, "")
            if not val:
                raise CommandSyntaxError(f"install: option {opt} needs a value")
            if opt == "--machine":
                machine = _int("install", val, "machine number", 0, MAX_MACHINE)
            elif opt == "--inputs":
                n_in = _int("install", val, "input count", 0, 8)
            elif opt == "--outputs":
                n_out = _int("install", val, "output count", 0, 8)
            elif opt == "--code":
                code = val
            elif opt == "--role":
                if val not in ("task", "exception", "assassin"):
                    raise CommandSyntaxError(
                        f"install: --role {val!r}: expected task, exception or assassin")
                role = val
            elif opt == "--level":
                level = _int("install", val, "level", 1)
            elif opt == "--param":
                k, v = _kv("install --param", val)
                params[k] = parse_value(v, f"install --param {k}", numbers_only_finite=True)
            elif opt == "--queue":
                k, v = _kv("install --queue", val)
                queued[k] = _int("install --queue", v, "queue length", 1)
            elif opt == "--restart":
                if val not in RESTART_POLICIES:
                    raise CommandSyntaxError(f"install: --restart {val!r}: expected "
                                             f"{', '.join(RESTART_POLICIES)}")
                restart = val
            elif opt == "--backoff":
                backoff = _seconds("install --backoff", val)
            else:
                raise CommandSyntaxError(
                    f"install: unknown option {opt} (expected -m#i#o#[s], --machine, --inputs, "
                    "--outputs, --code, --role, --level, --param, --queue, --standing, "
                    "--restart, --backoff)")
            continue
        if word.startswith("-") and len(word) > 1:
            raise CommandSyntaxError(f"install: bad option {word!r} (expected -m#i#o#)")
        rest.append(word)
    if machine is None:
        raise CommandSyntaxError("install: no machine given (expected -m#, e.g. -m0i2o1)")
    if not rest:
        raise CommandSyntaxError("install: no task given")
    if len(rest) == 1 and n_in is None and n_out is None and rest[0].split("/")[-1].startswith(
            "sysfile"):
        return Boot(machine, rest[0])
    name_word, files = rest[0], rest[1:]
    n_in = n_in if n_in is not None else 0
    n_out = n_out if n_out is not None else 0
    if n_in + n_out != len(files):
        raise CommandSyntaxError(
            f"install {name_word}: -i{n_in} -o{n_out} announce {n_in + n_out} file(s) after the "
            f"task, {len(files)} given ({' '.join(files) or 'none'})")
    name, eq, ref = name_word.partition("=")
    if eq:
        code = ref
    check_task_name("install", name)
    check_code("install " + name, code or name)
    return Install(name=name, machine=machine, inputs=tuple(files[:n_in]),
                   outputs=tuple(files[n_in:]), code=code or name, role=role, level=level,
                   params=params, queued=queued, standing=standing, restart=restart,
                   backoff=backoff)


def check_task_name(cmd: str, name: str) -> None:
    """Refuse a task name that breaks the rule: 1 to MAX_NAME characters, letters, digits,
    ``_ . -``, starting with a letter or ``_``. Raises CommandSyntaxError saying so."""
    if len(name) > MAX_NAME:
        raise CommandSyntaxError(f"{cmd}: task name {_short(name)} has {len(name)} characters; "
                                 f"a task name has at most {MAX_NAME}")
    if not NAME_PATTERN.fullmatch(name):
        raise CommandSyntaxError(f"{cmd}: task name {name!r} breaks the rule: letters, digits, "
                                 "_ . -, starting with a letter or _")


def check_code(cmd: str, code: str) -> None:
    """Refuse a task code reference that cannot name code: a module path (``pkg.mod``, with
    ``:function``) whose every part is a Python identifier, or a ``.py`` file (a path with
    ``/``) whose every part fits a file name. Raises CommandSyntaxError naming the rule."""
    if len(code) > MAX_CODE:
        raise CommandSyntaxError(f"{cmd}: code {_short(code)} has {len(code)} characters; at "
                                 f"most {MAX_CODE}")
    target, colon, func = code.partition(":")
    if colon and not func.isidentifier():
        raise CommandSyntaxError(f"{cmd}: code {code!r}: the function after ':' must be a "
                                 "Python identifier")
    if target.endswith(".py") or "/" in target:
        long = [part for part in target.split("/") if len(part) > MAX_FILE_PART]
        if long:
            raise CommandSyntaxError(f"{cmd}: code {_short(code)}: a file-name part has "
                                     f"{len(long[0])} characters; at most {MAX_FILE_PART}")
        return
    parts = target.split(".")
    if not all(_MODULE_PART.fullmatch(part) for part in parts):
        raise CommandSyntaxError(f"{cmd}: code {code!r} breaks the rule: a module path "
                                 "(pkg.module: parts of letters, digits, _ or -, no leading, "
                                 "trailing or doubled '.'), optionally ':function', or a .py "
                                 "file")
    if any(len(part) > MAX_FILE_PART - 3 for part in parts):  # looked up as PART.py
        raise CommandSyntaxError(f"{cmd}: code {_short(code)}: a module name has more than "
                                 f"{MAX_FILE_PART - 3} characters")


def _seconds(cmd: str, word: str) -> float:
    """A finite, non-negative number of seconds at most one day."""
    try:
        v = float(word)
    except ValueError:
        raise CommandSyntaxError(f"{cmd}: {word!r} is not a number of seconds") from None
    if not 0.0 <= v <= 86400.0:  # also refuses nan and inf
        raise CommandSyntaxError(f"{cmd}: {word!r}: expected seconds in 0..86400")
    return v


def _priority_word(cmd: str, args: list[str]) -> tuple[int | None, list[str]]:
    prio: int | None = None
    rest: list[str] = []
    it = iter(args)
    for word in it:
        m = _PRIO.match(word)
        if m:
            prio = _int(cmd, m.group(1), "priority", PRIORITIES[0], PRIORITIES[-1])
        elif word in ("-p", "--priority"):
            prio = _int(cmd, next(it, ""), "priority", PRIORITIES[0], PRIORITIES[-1])
        elif word.startswith("--priority="):
            prio = _int(cmd, word.split("=", 1)[1], "priority", PRIORITIES[0], PRIORITIES[-1])
        else:
            rest.append(word)
    return prio, rest


# printable ASCII and shlex' whitespace, without quotes, backslash and '#' (see parse)
_PLAIN = re.compile(r"[ \t\r\n!$-&(-\[\]-~]*")


def parse(line: str | list[str]) -> Request | None:
    """Parse one host command line; None for a blank line or a comment.

    Raises CommandSyntaxError naming the command and the offending word, and for a line longer
    than MAX_LINE characters (refused before any parsing).
    """
    if isinstance(line, str) and len(line) > MAX_LINE:
        raise CommandSyntaxError(f"{_short(line.strip())}: a command line of {len(line)} "
                                 f"characters; at most {MAX_LINE}")
    if isinstance(line, str) and _PLAIN.fullmatch(line):
        words = line.split()   # no quote, escape or comment: what shlex would give, 10x faster
    elif isinstance(line, str):
        try:
            words = shlex.split(line, comments=True)
        except ValueError as exc:
            raise CommandSyntaxError(f"{_short(line.strip())}: {exc} (an unbalanced quote); "
                                     f"expected every ' and \" closed") from None
    else:
        words = list(line)
    if not words:
        return None
    cmd, args = words[0], words[1:]
    if cmd == "install":
        return _install(args)
    if cmd == "setpri":
        prio, rest = _priority_word("setpri", args)
        if prio is None:
            raise CommandSyntaxError(
                "setpri: no priority given (expected -#, e.g. setpri -9 A4 C1)")
        if len(rest) != 2:
            raise CommandSyntaxError(
                f"setpri: expected srctsk dsttsk, got {' '.join(rest) or 'none'}")
        return SetPri(prio, rest[0], rest[1])
    if cmd == "invoke":
        prio, rest = _priority_word("invoke", args)
        if not rest:
            raise CommandSyntaxError("invoke: no task given")
        command = dict(_kv("invoke", w) for w in rest[1:])
        return Invoke(rest[0], {k: parse_value(v, f"invoke {rest[0]} {k}",
                                               numbers_only_finite=True)
                                for k, v in command.items()}, prio)
    if cmd in ("suspend", "resume", "close"):
        if len(args) != 1:
            raise CommandSyntaxError(f"{cmd}: expected one task name")
        return TaskOp(cmd, args[0])
    if cmd == "resetpri":
        if len(args) == 1:
            return TaskOp(cmd, args[0])
        if len(args) == 2:
            return ResetPri(args[0], args[1])
        raise CommandSyntaxError("resetpri: expected a task (resetpri T) or a link "
                                 "(resetpri SRC DST)")
    if cmd == "reset":
        if len(args) > 1:
            raise CommandSyntaxError("reset: expected at most one task name")
        return TaskOp(cmd, args[0] if args else "")
    if cmd == "inject":
        if len(args) < 2:
            raise CommandSyntaxError("inject: expected a device and a value")
        return Inject(args[0], parse_value(" ".join(args[1:]), f"inject {args[0]}"))
    if cmd == "map":
        return ShowMap()
    if cmd == "axis":
        return _axis(args)
    if cmd == "nmt":
        return _nmt(args)
    raise CommandSyntaxError(
        f"unknown command {cmd!r} (expected install, setpri, resetpri, invoke, suspend, "
        "resume, close, reset, inject, axis, nmt or map)")


def _nmt(args: list[str]) -> NmtCmd:
    usage = f"nmt {'|'.join(NMT_WORDS)} NODE [BUS]"
    if len(args) not in (2, 3):
        raise CommandSyntaxError(f"nmt: expected {usage}, got {' '.join(args) or 'nothing'}")
    word = args[0]
    if word not in NMT_WORDS:
        raise CommandSyntaxError(f"nmt: unknown command {word!r}; expected one of "
                                 f"{', '.join(NMT_WORDS)}")
    node = _int(f"nmt {word}", args[1], "node id", 1, 127)
    return NmtCmd(word, node, args[2] if len(args) == 3 else "")


def _axis(args: list[str]) -> AxisCmd:
    if not args:
        raise CommandSyntaxError(f"axis: no axis given (expected axis NAME "
                                 f"[{'|'.join(AXIS_WORDS)}])")
    device, rest = args[0], args[1:]
    word = rest[0] if rest else "status"
    if word not in AXIS_WORDS:
        raise CommandSyntaxError(f"axis {device}: unknown command {word!r}; expected one of "
                                 f"{', '.join(AXIS_WORDS)}")
    if word == "set-mode":
        if len(rest) > 2:
            raise CommandSyntaxError(f"axis {device} set-mode: expected at most one mode, got "
                                     f"{' '.join(rest[1:])}")
        return AxisCmd(device, word, rest[1] if len(rest) == 2 else "")
    if len(rest) > 1:
        raise CommandSyntaxError(f"axis {device} {word}: takes no argument, got "
                                 f"{' '.join(rest[1:])}")
    return AxisCmd(device, word)
