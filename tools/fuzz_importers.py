"""fuzz_importers - ``chcos import`` on thousands of mutations of the shipped vendor files.

Each case takes one shipped vendor file (EDS, DBC, register list, SunSpec device file), applies
one to three seeded mutations (a number made extreme: ``1e400``, ``nan``, ``4294967296``, 40
digits; a line deleted, doubled or swapped; a 140 kB field; a stray quote or separator; the file
cut short) and sometimes a random ``--prefix`` or ``--bus``, runs ``chcos import`` in this
process and classifies what happened:

* **traceback**: an exception escaped the command (anything but its exit status);
* **hang**: the case ran longer than ``--hang`` seconds (interrupted by a timer);
* **invalid output**: the import wrote a map that ``chcos check`` then refuses;
* **unlocated refusal**: a refusal whose message names neither a line, a row, a section, a
  key nor an option (a refusal of the file as a whole, "no signals to import", is counted
  apart: there is no line to name);
* the slowest case in seconds per megabyte of input (the target: at most 1 s/MB).

Run it as ``.venv/bin/python -m tools.fuzz_importers --cases 6000`` (about ten minutes on a
quiet machine); ``--seed`` makes a run repeatable; ``--report FILE`` writes every finding as
JSON (keep it out of the source tree). Exit status 1 when anything but refusals was found.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import logging
import random
import re
import resource
import signal
import sys
import tempfile
import time
import traceback
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
#: the shipped vendor files and the import command of each kind
SOURCES = {
    "eds": ["docs/vendor/drive.eds", "docs/vendor/io_module.eds",
            "vcan_tests/vendor/acme_amd200.eds", "vcan_tests/vendor/awkward_ax7.eds"],
    "dbc": ["docs/vendor/gripper.dbc", "docs/vendor/vehicle.dbc",
            "vcan_tests/vendor/hpu_press.dbc", "vcan_tests/vendor/journey/awkward.dbc"],
    "modbus": ["docs/vendor/meter.csv", "vcan_tests/vendor/plc_registers.csv",
               "vcan_tests/vendor/modicon_list.csv", "vcan_tests/vendor/journey/meter.csv"],
    "sunspec": ["docs/vendor/inverter.json"],
}
EXTREMES = ["1e400", "nan", "-inf", "-1", "0", "4294967296", "1000000", "9" * 40, "0x",
            "0xFFFFFFFFF", "", "65536", "-32769", "1.5", "3.4e39", "$NODEID+0x80000000"]
NAMES = ["", "x", "9bad", "a b", "é", "a" * 70, "ok_", "-x", "a.b", "a\"b", "\u0000", "bus-1"]
#: what a located refusal names
LOCATED = re.compile(r"line\s+\d+|row \d+|\[[0-9A-Za-z]+\]|\bbus\[|\bdevice\[|models\[|--\w|"
                     r"\.toml:\d+|key \w+|header|0x[0-9A-F]{4}|: [A-Za-z_]+\.[A-Za-z_]")
#: a refusal of the file as a whole (nothing in it to import): it names the file and what is
#: missing, and there is no line to name
WHOLE_FILE = re.compile(r"no signals to import|no PDO-mapped or application object|expected a "
                        r"header row|no register the modbus driver|key models:")


@dataclass
class Findings:
    """What a run found, by class, with a few examples of each."""

    counts: Counter[str] = field(default_factory=Counter)
    examples: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    worst_s_per_mb: float = 0.0
    worst_case: str = ""

    def add(self, kind: str, case: dict[str, Any], keep: int = 20) -> None:
        self.counts[kind] += 1
        self.examples.setdefault(kind, [])
        if len(self.examples[kind]) < keep:
            self.examples[kind].append(case)


def mutate(text: str, rng: random.Random) -> tuple[str, list[str]]:
    """``text`` with one to three mutations; returns it and what was done."""
    done = []
    for _ in range(rng.randint(1, 3)):
        lines = text.splitlines()
        if not lines:
            break
        i = rng.randrange(len(lines))
        op = rng.choice(["number", "number", "number", "delete", "double", "swap", "field",
                         "char", "cut"])
        if op == "number":
            numbers = list(re.finditer(r"(?<![A-Za-z_])-?(?:0x[0-9A-Fa-f]+|\d+(?:\.\d+)?)",
                                       lines[i]))
            if not numbers:
                continue
            m = rng.choice(numbers)
            new = rng.choice(EXTREMES)
            lines[i] = lines[i][:m.start()] + new + lines[i][m.end():]
            done.append(f"line {i + 1}: {m.group(0)!r} -> {new[:20]!r}")
        elif op == "delete":
            del lines[i]
            done.append(f"line {i + 1} deleted")
        elif op == "double":
            lines.insert(i, lines[i])
            done.append(f"line {i + 1} doubled")
        elif op == "swap":
            j = rng.randrange(len(lines))
            lines[i], lines[j] = lines[j], lines[i]
            done.append(f"lines {i + 1} and {j + 1} swapped")
        elif op == "field":
            at = rng.randrange(len(lines[i]) + 1)
            lines[i] = lines[i][:at] + "A" * 140_000 + lines[i][at:]
            done.append(f"line {i + 1}: a 140 kB field")
        elif op == "char":
            at = rng.randrange(len(lines[i]) + 1)
            ch = rng.choice(['"', ";", ",", "|", "@", "[", "]", "=", "\t", "\x00", "é", ":"])
            lines[i] = lines[i][:at] + ch + lines[i][at:]
            done.append(f"line {i + 1}: {ch!r} inserted")
        else:
            cut = rng.randrange(len(text) + 1)
            text = text[:cut]
            done.append(f"cut at {cut}")
            continue
        text = "\n".join(lines) + "\n"
    return text, done


class _Hang(BaseException):
    """The timer's interruption: a BaseException, so no ``except Exception`` of the code under
    test swallows it."""


def _alarm(_sig: int, _frame: Any) -> None:
    raise _Hang()


def _disarm() -> None:
    """Stop the hang timer, even if it fires once more while it is being stopped."""
    while True:
        try:
            signal.setitimer(signal.ITIMER_REAL, 0)
            return
        except _Hang:
            continue


def args_for(kind: str, path: Path, out: Path, rng: random.Random) -> list[str]:
    """The ``chcos import`` arguments of a case."""
    argv = [kind, str(path), "-o", str(out)]
    if kind == "eds":
        argv += ["--node", str(rng.choice([1, 5, 127]))]
    elif kind in ("modbus", "sunspec"):
        argv += ["--host", "127.0.0.1"]
    if rng.random() < 0.1:
        argv += ["--prefix", rng.choice(NAMES)]
    if rng.random() < 0.1:
        argv += ["--bus", rng.choice(NAMES)]
    return argv


def run_case(kind: str, source: Path, rng: random.Random, work: Path, hang: float,
             findings: Findings) -> None:
    """One mutated import, classified into ``findings``."""
    from chcos.devices.devmap import check
    from chcos.devices.importers import main as import_main

    text, done = mutate(source.read_text(encoding="utf-8", errors="replace"), rng)
    path = work / source.name
    path.write_text(text, encoding="utf-8", errors="replace")
    out = work / "out.toml"
    out.unlink(missing_ok=True)
    argv = args_for(kind, path, out, rng)
    case: dict[str, Any] = {"source": str(source.relative_to(ROOT)), "mutations": done,
            "args": [a[:60] for a in argv[2:]]}
    err = io.StringIO()
    start = time.perf_counter()
    signal.setitimer(signal.ITIMER_REAL, hang, 1.0)   # again each second, should one be lost
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            status = import_main(argv)
    except SystemExit as exc:          # argparse refused an option
        status = int(exc.code or 0)
    except _Hang:
        findings.add("hang", case)
        return
    except BaseException as exc:       # what the fuzz is for
        case["traceback"] = traceback.format_exception_only(type(exc), exc)[-1][:300]
        findings.add("traceback", case)
        return
    finally:
        _disarm()
    seconds = time.perf_counter() - start
    per_mb = seconds / max(len(text.encode("utf-8", errors="replace")) / 1e6, 1.0)
    if per_mb > findings.worst_s_per_mb:
        findings.worst_s_per_mb, findings.worst_case = per_mb, json.dumps(case)[:300]
    message = err.getvalue().strip().splitlines()[-1:] or [""]
    if status == 0 and out.exists():
        dmap, errors, _ = check([out])
        if dmap is None:
            case["errors"] = [e[:200] for e in errors[:3]]
            findings.add("invalid output", case)
        else:
            findings.add("written", case, keep=0)
    elif status == 2:
        case["message"] = message[0][:300]
        text = message[0].replace(str(path), "FILE")
        if WHOLE_FILE.search(text):
            findings.add("refused (the whole file)", case, keep=3)
        elif LOCATED.search(text):
            findings.add("refused", case, keep=0)
        else:
            findings.add("unlocated refusal", case)
    else:
        case["status"] = status
        findings.add("other status", case)


def _report(path: str | None, cases: int, seed: int, started: float,
            findings: Findings) -> dict[str, Any]:
    """The summary of the first ``cases`` cases, also written with the examples to ``path``."""
    summary = {"cases": cases, "seed": seed,
               "seconds": round(time.perf_counter() - started, 1),
               "counts": dict(findings.counts),
               "worst_seconds_per_MB": round(findings.worst_s_per_mb, 3),
               "worst_case": findings.worst_case}
    if path:
        Path(path).write_text(json.dumps({"summary": summary, "examples": findings.examples},
                                         indent=2), encoding="utf-8")
    return summary


def main(argv: list[str] | None = None) -> int:
    """Run the fuzz; print the counts; 1 when a traceback, hang or invalid output was found."""
    ap = argparse.ArgumentParser(prog="python -m tools.fuzz_importers", description=__doc__)
    ap.add_argument("--cases", type=int, default=6000)
    ap.add_argument("--seed", type=int, default=49)
    ap.add_argument("--hang", type=float, default=20.0,
                    help="seconds after which a case counts as a hang (default 20)")
    ap.add_argument("--kinds", default="eds,dbc,modbus,sunspec")
    ap.add_argument("--report", help="write the findings as JSON here")
    args = ap.parse_args(argv)
    logging.disable(logging.WARNING)        # the EDS reader's per-field warnings
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    resource.setrlimit(resource.RLIMIT_AS, (4 * 2**30, hard))   # a 9 GB case fails, not the box
    signal.signal(signal.SIGALRM, _alarm)
    rng = random.Random(args.seed)
    kinds = [k for k in args.kinds.split(",") if k in SOURCES]
    findings = Findings()
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="chcos-fuzz-") as tmp:
        for n in range(args.cases):
            kind = kinds[n % len(kinds)]
            source = ROOT / rng.choice(SOURCES[kind])
            run_case(kind, source, rng, Path(tmp), args.hang, findings)
            if args.report and (n + 1) % 250 == 0:      # a long run's findings so far
                _report(args.report, n + 1, args.seed, started, findings)
    resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
    summary = _report(args.report, args.cases, args.seed, started, findings)
    print(json.dumps(summary, indent=2))
    bad = sum(findings.counts[k] for k in ("traceback", "hang", "invalid output"))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
