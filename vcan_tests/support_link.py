"""support_link - helpers for the link tests: a child satellite process and thread-safe collectors.

Run as a child process: ``python -m vcan_tests.support_link --listen P --connect Q ...``. The
child opens a :class:`chcos.comm.Transport`, optionally serves a key with a fixed answer, echoes
one key onto another, watches liveliness tokens (printing ``join``/``leave`` events) and
announces a token, then prints one JSON line ``{"event": "ready", "zid": ..., "peers": [...]}``
on stdout; with ``--fetch KEY TOKEN`` it then waits for TOKEN to join (it must
watch it), requests KEY and prints ``{"event": "fetched",
"answer": ...}``. It answers ``peers`` lines on stdin
with ``{"event": "peers", "peers": [...]}`` and exits cleanly when stdin closes.

In the tests, :class:`Child` starts such a process and waits on its output with timeouts (never
sleeps); :class:`Collector` gathers callback calls from Zenoh threads into a queue.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import queue
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from chcos.comm import (
    LinkConfig,
    MessageKind,
    TlsSettings,
    Transport,
    UsrPwdAuth,
    enable_zenoh_logging,
)
from chcos.comm.config import DEFAULT_LEASE_MS

REPO = Path(__file__).resolve().parent.parent
WAIT = 10.0  # seconds: upper bound of any single wait in the link tests


class Collector:
    """A queue of whatever callbacks on Zenoh threads hand it; ``get`` waits with a timeout."""

    def __init__(self) -> None:
        self._q: queue.Queue[Any] = queue.Queue()

    def __call__(self, *args: Any) -> None:
        self._q.put(args[0] if len(args) == 1 else args)

    def get(self, timeout: float = WAIT) -> Any:
        """The next item; raises AssertionError if none came within ``timeout`` seconds."""
        try:
            return self._q.get(timeout=timeout)
        except queue.Empty:
            raise AssertionError(f"nothing arrived within {timeout} s") from None

    def get_until(self, wanted: Any, timeout: float = WAIT) -> list[Any]:
        """Items up to and including the first equal to ``wanted`` (AssertionError on timeout)."""
        seen = []
        while True:
            item = self.get(timeout)
            seen.append(item)
            if item == wanted:
                return seen

    def empty(self) -> bool:
        """True if nothing is queued right now."""
        return self._q.empty()


class Child:
    """A child satellite process; reads its stdout (JSON events) and stderr (log) in threads."""

    def __init__(self, args: Sequence[str]) -> None:
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
        env.pop("RUST_LOG", None)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "vcan_tests.support_link", *args],
            cwd=REPO,
            env=env,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.events: queue.Queue[dict[str, Any]] = queue.Queue()
        self.log: queue.Queue[str] = queue.Queue()
        self.log_lines: list[str] = []
        self._pending: list[dict[str, Any]] = []
        threading.Thread(target=self._read_stdout, daemon=True).start()
        threading.Thread(target=self._read_stderr, daemon=True).start()

    def _read_stdout(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.events.put(json.loads(line))
        self.events.put({"event": "eof"})

    def _read_stderr(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.log_lines.append(line)
            self.log.put(line)

    def expect(self, event: str, timeout: float = WAIT, **fields: Any) -> dict[str, Any]:
        """The first stdout event named ``event`` (with these field values) not yet taken; other
        events stay pending for later calls. AssertionError if none comes within ``timeout``."""

        def matches(ev: dict[str, Any]) -> bool:
            return ev["event"] == event and all(ev.get(k) == v for k, v in fields.items())

        for i, ev in enumerate(self._pending):
            if matches(ev):
                return self._pending.pop(i)
        deadline = time.monotonic() + timeout
        while True:
            try:
                ev = self.events.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise AssertionError(
                    f"child sent no {event!r} {fields} within {timeout} s; pending "
                    f"{self._pending}; stderr: {''.join(self.log_lines)}"
                ) from None
            if matches(ev):
                return ev
            if ev["event"] == "eof":
                raise AssertionError(
                    f"child ended before {event!r}: exit {self.proc.wait(WAIT)}, "
                    f"stderr: {''.join(self.log_lines)}"
                )
            self._pending.append(ev)

    def wait_log(self, fragment: str, timeout: float = WAIT) -> str:
        """The next stderr line containing ``fragment`` (AssertionError on timeout)."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                line = self.log.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise AssertionError(
                    f"no log line with {fragment!r} within {timeout} s: {self.log_lines}"
                ) from None
            if fragment in line:
                return line

    def peers(self) -> list[str]:
        """Ask the child which peers its session has."""
        assert self.proc.stdin is not None
        self.proc.stdin.write("peers\n")
        self.proc.stdin.flush()
        return list(self.expect("peers")["peers"])

    def kill(self) -> None:
        """SIGKILL the child (no clean shutdown) and reap it."""
        self.proc.kill()
        self.proc.wait(timeout=WAIT)

    def stop(self) -> int:
        """Close its stdin (it exits cleanly) and return its exit code."""
        if self.proc.poll() is None:
            assert self.proc.stdin is not None
            with contextlib.suppress(BrokenPipeError):
                self.proc.stdin.close()
            try:
                return self.proc.wait(timeout=WAIT)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=WAIT)
                raise AssertionError("child did not exit after stdin closed") from None
        return self.proc.returncode

    def __enter__(self) -> Child:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=WAIT)
        for stream in (self.proc.stdin, self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()


def child_args(
    *,
    listen: int | None = None,
    connect: Sequence[int] = (),
    token: str | None = None,
    serve: tuple[str, str] | None = None,
    echo: tuple[str, str] | None = None,
    auth: tuple[str, str, Path | None] | None = None,
    watch: str | None = None,
    fetch: tuple[str, str] | None = None,
    lease_ms: int | None = None,
    tls: tuple[Path, Path, Path] | None = None,
    zenoh_log: str | None = None,
) -> list[str]:
    """The command-line arguments for a child with these options."""
    args: list[str] = []
    if listen is not None:
        args += ["--listen", str(listen)]
    for port in connect:
        args += ["--connect", str(port)]
    if token is not None:
        args += ["--token", token]
    if serve is not None:
        args += ["--serve", serve[0], serve[1]]
    if echo is not None:
        args += ["--echo", echo[0], echo[1]]
    if auth is not None:
        args += ["--user", auth[0], "--password", auth[1]]
        if auth[2] is not None:
            args += ["--dictionary", str(auth[2])]
    if watch is not None:
        args += ["--watch", watch]
    if fetch is not None:
        args += ["--fetch", fetch[0], fetch[1]]
    if tls is not None:
        args += ["--tls", *(str(x) for x in tls)]
    if lease_ms is not None:
        args += ["--lease-ms", str(lease_ms)]
    if zenoh_log is not None:
        args += ["--zenoh-log", zenoh_log]
    return args


_emit_lock = threading.Lock()
_events: list[Any] = []  # the child's event stream (the original stdout), once main() ran


def _emit(event: str, **fields: Any) -> None:
    with _emit_lock:
        out = _events[0]
        out.write(json.dumps({"event": event, **fields}) + "\n")
        out.flush()


def main(argv: Sequence[str] | None = None) -> int:
    """The child satellite: see the module docstring."""
    p = argparse.ArgumentParser(prog="support_link")
    p.add_argument("--listen", type=int)
    p.add_argument("--connect", type=int, action="append", default=[])
    p.add_argument("--token")
    p.add_argument("--serve", nargs=2, metavar=("KEY", "ANSWER"))
    p.add_argument("--echo", nargs=2, metavar=("IN", "OUT"))
    p.add_argument("--watch")
    p.add_argument("--fetch", nargs=2, metavar=("KEY", "AFTER_TOKEN"))
    p.add_argument("--user")
    p.add_argument("--password")
    p.add_argument("--dictionary")
    p.add_argument("--tls", nargs=3, metavar=("CA", "CERT", "KEY"))
    p.add_argument("--lease-ms", type=int, default=DEFAULT_LEASE_MS)
    p.add_argument("--zenoh-log", metavar="FILTER")
    a = p.parse_args(argv)
    # Zenoh's log writes to file descriptor 1: keep the real stdout for events only and send
    # everything else written to fd 1 to stderr.
    _events.append(os.fdopen(os.dup(1), "w", encoding="utf-8"))
    os.dup2(2, 1)
    if a.zenoh_log:
        enable_zenoh_logging(a.zenoh_log)
    auth = None
    if a.user is not None:
        auth = UsrPwdAuth(a.user, a.password, Path(a.dictionary) if a.dictionary else None)
    tls = None
    if a.tls is not None:
        ca, cert, key = (Path(x) for x in a.tls)
        tls = TlsSettings(ca, listen_certificate=cert, listen_private_key=key)
    config = LinkConfig(a.listen, tuple(a.connect), lease_ms=a.lease_ms, auth=auth, tls=tls)
    with Transport(config) as link:
        if a.serve is not None:
            answer = a.serve[1].encode()
            link.serve(a.serve[0], lambda _payload: answer)
        if a.echo is not None:
            out = a.echo[1]

            def echo(_key: str, payload: bytes) -> None:
                link.publish(out, payload, priority=80, kind=MessageKind.COMMAND)

            link.subscribe(a.echo[0], echo)
        seen: dict[str, threading.Event] = {}
        if a.fetch is not None:
            seen[a.fetch[1]] = threading.Event()
        if a.watch is not None:

            def on_join(key: str) -> None:
                if key in seen:
                    seen[key].set()
                _emit("join", key=key)

            link.watch(a.watch, on_join, lambda key: _emit("leave", key=key))
        if a.token is not None:
            link.announce(a.token)
        _emit("ready", zid=link.zid, peers=link.peers())
        if a.fetch is not None:
            # the server is reachable once its owner's token is seen (connections are async)
            if not seen[a.fetch[1]].wait(WAIT):
                raise SystemExit(f"token {a.fetch[1]} never seen; cannot fetch {a.fetch[0]}")
            _emit("fetched", answer=link.request(a.fetch[0], timeout=WAIT).decode())
        for line in sys.stdin:
            if line.strip() == "peers":
                _emit("peers", peers=link.peers())
    return 0


if __name__ == "__main__":
    sys.exit(main())
