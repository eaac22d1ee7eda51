"""satellite - one machine of a CHC-OS system, in its own process, on the Zenoh link.

A satellite runs the kernel, tasks and devices of its machine and keeps a copy of the whole system
tables, which every satellite builds from the same *install log*: the host's install, setpri and
boot commands in the order they were committed (thesis 6: "every processor keeps the same
message table, updated by broadcast at each install"). Each log entry is a plain host command
line. A host command that changes the tables goes in three steps, driven by the host
(:mod:`chcos.satellites.host`) over the satellites it found up, the lowest-numbered of them
being the *sequencer*:

1. ``prepare`` (every live satellite checks the line against its tables at the log length
   ``seq`` the host read from the sequencer; nobody imports any code, the task's satellite only
   checks that its code reference names a module on the Python path or a file inside the
   system's task path); each answers the entry it holds *accepted but uncommitted* at ``seq``,
   if any;
2. ``accept`` on the sequencer first (a compare-and-set: its log has exactly ``seq`` entries
   and it holds no other uncommitted entry at ``seq``; a host that lost the race to another
   host is told so, :class:`RaceLost`, and starts again at the new length), then on every
   other live satellite: each saves the line as its uncommitted entry ``seq``
   (``m<N>.pending``, fsync'd) and applies nothing;
3. ``commit`` on the sequencer first, then everywhere else: the entry is applied and appended
   to the committed log ``m<N>.log`` (fsync'd), and the uncommitted copy removed.

**Why the logs cannot diverge.** An entry enters a committed log only after every live
satellite holds it durably (step 2 before step 3), so whoever of them is up next holds it,
committed or accepted. A host (this one retrying, or any other) that finds an accepted entry at
the log's end - on the sequencer (``head``) or on any satellite (``prepare``) - completes *that*
entry first (accept everywhere, commit), before its own line: the entry may have been
committed by a sequencer that died since, and completing it is the one choice that agrees with
every outcome. A restarted satellite keeps its committed log and drops its uncommitted entry
once its peers' committed log covers that position, logging whether the peers hold the same
line there (it was committed) or another one (it never was: nobody had been told it was);
alone, it keeps it for the next host to complete. So a committed entry is never lost and never
contradicted while at least one satellite that held it is up; the host's answer is what the
replicated log holds (:meth:`chcos.satellites.host.Host.execute`). The limit, stated: the
membership is "every satellite up", not a quorum (one satellite alone keeps its machine
running and takes installs, as the thesis' system does), so if every satellite that holds a
committed entry is down while the others commit a different entry at that position (a
partition), the two logs contradict: the returning satellite refuses to start naming the first
entry that differs (below), never silently.

Code named by an install is imported only when the committed entry is applied on the task's own
satellite; if it then fails to load, the task is still entered in the tables (so every satellite
numbers its links alike) but raises when invoked, and the host is told why.

A satellite that starts late or restarts fetches the log from a live member before it runs
anything, checks that it is a list of install lines that extends its own, and applies each entry
as an install would be; with nobody up it replays its own saved install log ``m<N>.log`` from
the system's state directory (or, without one, its sysfile.map there). A satellite
whose saved log is longer than its peers' and extends theirs replays its own (the host then
brings the sequencer up to date); one whose committed log contradicts its peers' refuses to
start, naming the first entry that differs. Runtime commands (invoke, suspend, resume, close,
inject) go only to the satellite that runs the task or device.

Tests only: ``CHCOS_TEST_CRASH_AT=PHASE:WHEN`` (``prepare``/``accept``/``commit``, ``before``
or ``after`` the step's durable effect) makes the satellite SIGKILL itself at that point of
its first such request, so a test can stop it at every step of the commit path
deterministically.

Control keys, under ``chcos/<system>``: ``m/<N>/ctl`` (host requests to machine N, JSON; only
payloads sealed by the host role are accepted), ``log`` and ``m/<N>/log`` (the install log, to
any member).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import logging
import os
import signal
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from chcos.comm.manager import CommManager
from chcos.comm.secret import Throttle
from chcos.comm.transport import Subscription, Transport
from chcos.errors import ChcosError, ConfigError, InstallError, LinkError, MessageError
from chcos.kernel.clock import Clock, RealClock
from chcos.satellites import control
from chcos.satellites.installlog import (
    MUTATING,
    append_log,
    clear_pending,
    code_problem,
    parse_log,
    read_log,
    read_pending,
    write_log,
    write_pending,
)
from chcos.satellites.sysfile import SystemFile, link_config_for
from chcos.system import cmdline, sysmap
from chcos.system.embedded import System
from chcos.tables.messages import PRIORITIES, PRIORITY_TEXT
from chcos.user.context import TaskContext

MAP_ANSWERS = 8
"""Map answers a satellite keeps for their pages (hosts reading them at the same time)."""

log = logging.getLogger("chcos.satellites.satellite")

#: How long a starting satellite keeps asking for the install log before it concludes that it is
#: alone (links to the other satellites are made in the background, within milliseconds).
CATCH_UP_WAIT = 2.0
#: Seconds between a change of the tables and the write of sysfile.map.
MAP_DELAY = 1.0
HOST_ONLY = frozenset({"host"})
MEMBERS = frozenset({"host", "satellite"})
SATELLITES = frozenset({"satellite"})
#: Stand-in code of a task whose own code failed to load after its install was committed.
FAILED_CODE = "chcos.satellites.satellite:code_failed"
_load_errors: dict[str, str] = {}


class RaceLost(InstallError):
    """Another host changed the install log first (or this satellite is not the sequencer):
    prepare again at the new log length."""


async def code_failed(ctx: TaskContext, cmd: Any) -> None:
    """The code of a task whose own code failed to load on its satellite: raises why."""
    raise InstallError(f"task {ctx.name}: {_load_errors.get(ctx.name, 'its code failed to load')}")


class Satellite:
    """Machine ``machine`` of the system described by ``sf``. Raises ConfigError if the
    system file has no such machine or its secret is unusable, LinkError if its port cannot be
    opened."""

    def __init__(self, sf: SystemFile, machine: int, *, clock: Clock | None = None) -> None:
        if machine not in sf.satellites:
            raise ConfigError(f"{sf.path}: no [[satellite]] with machine = {machine}")
        self.sf = sf
        self.machine = machine
        secret = sf.secret()
        sf.state_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
        self.transport = Transport(link_config_for(sf, machine, secret),
                                   sealer=secret.sealer("satellite", f"m{machine}"))
        try:
            self.system = System(sf.devmaps, clock=clock or RealClock(),
                                 task_path=sf.task_path, base_dir=sf.base_dir, map_path=None,
                                 local_machines={machine}, transport=self.transport,
                                 prefix=sf.prefix)
        except BaseException:
            self.transport.close()
            raise
        assert self.system.comm is not None  # built by System for its link
        self.comm: CommManager = self.system.comm
        self.log: list[str] = []
        #: the accepted, not yet committed entry (log position, line), saved in pending_path
        self.pending: tuple[int, str] | None = None
        self._crash_at = os.environ.get("CHCOS_TEST_CRASH_AT", "")
        self._lock = threading.RLock()
        self._map_lock = threading.Lock()
        self._map_answers: dict[str, str] = {}   # token -> the map answer's JSON text
        self._map_serial = itertools.count(1)
        self._subs: list[Subscription] = []
        self._stopping = threading.Event()
        self.refused: list[str] = []
        self.rejected = Throttle(log)
        self._map_timer: threading.Timer | None = None

    # ---- life -------------------------------------------------------------------------------
    def start(self) -> None:
        """Run the kernel, join the link, catch up with the install log, then serve the host."""
        self.system.start()
        self.comm.start()
        self.catch_up()
        p = self.sf.prefix
        self._subs.append(self.transport.serve(f"{p}/m/{self.machine}/ctl", self._control,
                                               roles=HOST_ONLY))
        for key in (f"{p}/log", f"{p}/m/{self.machine}/log"):
            self._subs.append(self.transport.serve(key, lambda _: self._log_bytes(),
                                                   roles=MEMBERS))
        self.comm.announce()
        log.info("satellite %d of %s up, %d log entries", self.machine, self.sf.name,
                 len(self.log))

    def stop(self) -> None:
        """Leave the link, write the map, stop the kernel, put actuators safe, stop the
        drivers."""
        self._stopping.set()
        timer = self._map_timer
        if timer is not None:
            timer.cancel()
            self.write_map()
        for sub in reversed(self._subs):
            sub.close()
        self._subs.clear()
        self.comm.stop()
        self.system.shutdown()
        self.transport.close()

    def __enter__(self) -> Satellite:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def rejected_counts(self) -> dict[str, int]:
        """How many payloads were refused or malformed so far, by cause (link, messages, host
        requests, install logs), and the link's seal refusals by kind, all receivers
        together (``link seal refused: replayed``...)."""
        out: dict[str, int] = {}
        for t in (self.transport.rejected, self.comm.rejected, self.rejected):
            out.update(t.counts)
        for kind, n in self.transport.refusals.items():
            if n:
                out[f"link seal refused: {kind}"] = n
        return out

    # ---- the install log ----------------------------------------------------------------------
    def _log_bytes(self) -> bytes:
        return json.dumps(list(self.log)).encode()  # a snapshot; no lock (peers may hold theirs)

    def log_hash(self) -> str:
        """SHA-256 of the install log (equal on satellites that hold the same log)."""
        return hashlib.sha256("\n".join(self.log).encode()).hexdigest()

    def catch_up(self, source: int | None = None, need: int = 0) -> int:
        """Apply the log entries this satellite misses, fetched from satellite ``source`` (None:
        any live one) until it holds at least ``need``; with none up at start, replay its own
        sysfile.map. Returns how many entries were applied. Raises LinkError if the fetched log
        does not extend this satellite's own (the logs diverged) or ``need`` entries could not
        be had, InstallError if an entry cannot be applied."""
        key = (f"{self.sf.prefix}/log" if source is None
               else f"{self.sf.prefix}/m/{source}/log")
        entries = None
        deadline = time.monotonic() + CATCH_UP_WAIT
        while True:  # links to peers come up in the background: give them a moment
            try:
                got = parse_log(self.transport.request(key, b"", timeout=1.5,
                                                       roles=SATELLITES))
                if len(got) >= need:
                    entries = got
                    break
            except LinkError as exc:
                if "malformed" in str(exc):
                    self.rejected.note("install log refused", str(exc))
            if time.monotonic() >= deadline or self._stopping.is_set():
                break
            self._stopping.wait(0.05)  # retry back-off
        with self._lock:
            start = not self.log
            saved = self._saved_log() if start else None
            if start:
                self.pending = read_pending(self.pending_path)
            if entries is None:
                if need:
                    raise LinkError(f"satellite {self.machine} needs log entry {need - 1} and "
                                    f"could not fetch it from {key}")
                path = self.sf.map_path(self.machine)
                if saved:
                    entries = saved
                    log.info("no satellite answered: replaying %s", self.log_path)
                elif start and path.exists():
                    entries = sysmap.install_lines(sysmap.read(path))
                    log.info("no satellite answered: reloading %s", path)
                else:
                    return 0
            elif saved and len(saved) > len(entries) and saved[:len(entries)] == entries:
                log.info("satellite %d holds %d log entries, its peers %d: replaying its own "
                         "(the host brings the peers up to date)", self.machine, len(saved),
                         len(entries))
                entries = saved
            held = saved or self.log
            if entries[:len(held)] != held[:len(entries)]:
                first = next(i for i, (a, b) in enumerate(zip(entries, held, strict=False))
                             if a != b)
                raise LinkError(f"satellite {self.machine}: the install log of {key} differs "
                                f"from this satellite's at entry {first}: {entries[first]!r} "
                                f"against {held[first]!r} (the logs diverged; move "
                                f"{self.log_path} away to take the peers' log)")
            n = 0
            try:
                for line in entries[len(self.log):]:
                    self._apply(line, persist=False)
                    n += 1
            finally:
                if start or n:
                    self._save_log()
                self._settle_pending()
            return n

    def _settle_pending(self) -> None:
        """Drop the uncommitted entry once the committed log covers its position (logged:
        the same line there means it was committed; another means it never was)."""
        if self.pending is None or self.pending[0] >= len(self.log):
            return
        seq, line = self.pending
        held = self.log[seq]
        if held == line:
            log.info("satellite %d: its uncommitted log entry %d was committed meanwhile "
                     "(%r)", self.machine, seq, line)
        else:
            log.warning("satellite %d: dropped its uncommitted log entry %d (%r): the peers "
                        "committed %r there (it was never committed)", self.machine, seq,
                        line, held)
        self._set_pending(None)

    def _set_pending(self, entry: tuple[int, str] | None) -> None:
        """Save (or remove) the uncommitted entry durably, then keep it."""
        if entry is None:
            clear_pending(self.pending_path)
        else:
            write_pending(self.pending_path, *entry)
        self.pending = entry

    def _crash_point(self, phase: control.Phase, when: str) -> None:
        """Tests: SIGKILL this process at ``phase``/``when`` if CHCOS_TEST_CRASH_AT says so
        (see the module doc)."""
        if self._crash_at == f"{phase.value}:{when}":
            log.warning("satellite %d: CHCOS_TEST_CRASH_AT=%s: killing myself", self.machine,
                        self._crash_at)
            for h in logging.getLogger().handlers:
                h.flush()
            os.kill(os.getpid(), signal.SIGKILL)

    def _map_changed(self) -> None:
        """Write sysfile.map MAP_DELAY seconds after the first change not yet written (the
        fsync'd install log is the durable record; the map is a view of it, so a burst of
        installs costs one map write instead of one per install)."""
        if self._map_timer is None and not self._stopping.is_set():
            self._map_timer = threading.Timer(MAP_DELAY, self.write_map)
            self._map_timer.daemon = True
            self._map_timer.start()

    def write_map(self) -> None:
        """Write this satellite's sysfile.map now (in the system's state directory)."""
        self._map_timer = None
        try:
            doc = self.system.call(self.system.sysmgr.map_doc)
            sysmap.write(self.sf.map_path(self.machine), doc)
        except (ChcosError, OSError) as exc:
            log.error("satellite %d: cannot write %s: %s", self.machine,
                      self.sf.map_path(self.machine), exc)

    @property
    def log_path(self) -> Path:
        """Where this satellite keeps its install log (one JSON string per line)."""
        return self.sf.state_dir / f"m{self.machine}.log"

    @property
    def pending_path(self) -> Path:
        """Where this satellite keeps its accepted, not yet committed, log entry."""
        return self.sf.state_dir / f"m{self.machine}.pending"

    def _saved_log(self) -> list[str]:
        """The install log this satellite saved last time ([] if none). Raises LinkError if the
        file is corrupt."""
        return read_log(self.log_path)

    def _save_log(self) -> None:
        """Write the whole install log (atomically, fsync'd)."""
        write_log(self.log_path, self.log)

    def _apply(self, line: str, persist: bool = True, committed: bool = False) -> str:
        """Validate ``line`` as an install would be and apply it as the next log entry (appended
        to the saved log if ``persist``). A ``committed`` entry (the host's commit: every live
        satellite prepared it at this log length) is checked against the tables only, not for
        its code, which then fails to load as any code may. Raises InstallError (nothing
        applied) if it is not valid here."""
        req = cmdline.parse(line)
        if not isinstance(req, MUTATING):
            raise InstallError(f"log entry {len(self.log)} ({line!r}) is not an install, setpri "
                               "or boot")
        self.system.call(self._check, req, not committed)
        try:
            answer = self.system.execute(req)
        except InstallError as exc:
            if not (isinstance(req, cmdline.Install) and req.machine == self.machine):
                raise
            _load_errors[req.name] = str(exc)
            log.error("satellite %d: %s", self.machine, exc)
            self.system.execute(replace(req, code=FAILED_CODE))
            answer = (f"{req.name} entered in the tables, but its code failed to load on machine "
                      f"{self.machine}: {exc}")
        self.log.append(line)
        self._map_changed()
        if persist:
            append_log(self.log_path, line)
        return answer

    # ---- host requests ----------------------------------------------------------------------
    def _control(self, payload: bytes) -> bytes:
        try:
            reply = self._serve(control.decode(payload))
        except ChcosError as exc:
            text = str(exc)
            self.refused.append(text)
            del self.refused[:-100]
            log.log(logging.INFO if isinstance(exc, RaceLost) else logging.WARNING,
                    "satellite %d refused a host request: %s", self.machine, text)
            reply = {"ok": False, "error": text, "type": type(exc).__name__}
        except (ValueError, KeyError, TypeError) as exc:
            text = f"malformed host request: {type(exc).__name__}: {exc}"
            self.rejected.note(f"satellite {self.machine}: malformed host request", text)
            reply = {"ok": False, "error": text, "type": "LinkError"}
        return json.dumps(reply, default=str).encode()

    def _map_page(self, req: control.MapRequest) -> dict[str, Any]:
        """One page of the map answer (see :class:`control.MapRequest`): part 0 without a
        token makes the answer's JSON text and keeps it (the last MAP_ANSWERS kept) so every
        page comes from the same map. Raises LinkError for a token no longer kept (the host
        asks again from part 0), TypeError for a part beyond the answer."""
        with self._map_lock:
            text = self._map_answers.get(req.token) if req.token else None
        token = req.token
        if text is None:
            if req.part != 0:
                raise LinkError(f"map answer {req.token!r} expired: ask again from part 0")
            doc = self.system.call(self.system.sysmgr.map_doc)
            text = json.dumps({"map": doc, "alive": sorted(self.comm.alive),
                               "rejected": self.rejected_counts()}, default=str)
            token = f"{self.machine}-{next(self._map_serial)}"
            with self._map_lock:
                self._map_answers[token] = text
                while len(self._map_answers) > MAP_ANSWERS:
                    del self._map_answers[next(iter(self._map_answers))]
        parts = max(1, -(-len(text) // control.MAP_PAGE))
        if req.part >= parts:
            raise TypeError(f"part: the map answer has {parts} page(s), got part {req.part}")
        page = text[req.part * control.MAP_PAGE:(req.part + 1) * control.MAP_PAGE]
        return {"ok": True, "page": page, "part": req.part, "parts": parts, "token": token}

    def _serve(self, req: control.ControlRequest) -> dict[str, Any]:
        """Answer one host request (see :mod:`chcos.satellites.control`). Raises ChcosError
        (refused: the host is told why), TypeError (malformed)."""
        if isinstance(req, control.MapRequest):
            return self._map_page(req)
        if isinstance(req, control.LogRequest):
            return {"ok": True, "log": list(self.log)}
        if isinstance(req, control.HelloRequest):  # answered at once, kernel busy or not
            return {"ok": True, "machine": self.machine, "nonce": req.nonce}
        if isinstance(req, control.HeadRequest):
            with self._lock:
                return {"ok": True, "length": len(self.log), "hash": self.log_hash(),
                        "pending": self._pending_at(len(self.log))}
        if isinstance(req, control.SyncRequest):  # the host found this one behind another
            if req.source not in self.sf.satellites or req.source == self.machine:
                raise TypeError("sync: expected another machine and a log length")
            with self._lock:
                return {"ok": True, "applied": self.catch_up(req.source, need=req.need)}
        parsed = cmdline.parse(req.line)
        if parsed is None:
            return {"ok": True, "answer": ""}
        if isinstance(req, control.ExecRequest):
            if isinstance(parsed, MUTATING):
                raise InstallError(f"{req.line!r} changes the tables: it must be prepared and "
                                   "committed on every satellite")
            return {"ok": True, "answer": self.system.execute(parsed)}
        if not isinstance(parsed, MUTATING):
            raise InstallError(f"{req.line!r} does not change the tables: send it with exec")
        if req.leader is not None and req.leader not in self.sf.satellites:
            raise TypeError("leader: expected a machine of the system")
        return self._change(req, parsed)

    def _pending_at(self, seq: int) -> str | None:
        """The uncommitted entry held at log position ``seq``, if any."""
        return self.pending[1] if self.pending is not None and self.pending[0] == seq else None

    def _change(self, req: control.ChangeRequest, parsed: cmdline.Request) -> dict[str, Any]:
        """One step (prepare, accept, commit; see the module doc) of a table change. Raises
        RaceLost when the log moved on (another host, or this satellite is not the sequencer),
        InstallError when the line is refused here or contradicts the committed log."""
        seq, line, phase = req.seq, req.line, req.phase
        leads = req.leader == self.machine
        with self._lock:
            self._crash_point(phase, "before")
            if seq > len(self.log) and not leads:
                self.catch_up(req.leader, need=seq)
            if seq < len(self.log):
                held = self.log[seq]
                if phase is control.Phase.PREPARE or held != line:
                    if phase is control.Phase.COMMIT:
                        raise InstallError(f"satellite {self.machine}: log entry {seq} is "
                                           f"{held!r}, not {line!r} (the logs diverged)")
                    raise RaceLost(f"satellite {self.machine} has {len(self.log)} log entries, "
                                   f"the host expected {seq}: another host changed the log "
                                   f"(entry {seq} is {held!r})")
                return {"ok": True, "answer": "already applied", "seq": seq}
            if seq != len(self.log):
                raise RaceLost(f"log entry {seq} is beyond the sequencer's log "
                               f"({len(self.log)} entries): another host changed the log")
            if phase is control.Phase.PREPARE:
                self.system.call(self._check, parsed)
                self._crash_point(phase, "after")
                return {"ok": True, "seq": seq, "pending": self._pending_at(seq)}
            if phase is control.Phase.ACCEPT:
                self._accept(seq, line, leads)
                self._crash_point(phase, "after")
                return {"ok": True, "seq": seq}
            if leads and self._pending_at(seq) != line:  # COMMIT on the sequencer
                raise RaceLost(f"satellite {self.machine} did not accept {line!r} as log entry "
                               f"{seq}: prepare again")
            answer = self._apply(line, committed=True)
            self._set_pending(None)
            self._crash_point(phase, "after")
            return {"ok": True, "answer": answer, "seq": seq}

    def _accept(self, seq: int, line: str, leads: bool) -> None:
        """Save ``line`` as the uncommitted entry ``seq``; on the sequencer a compare-and-set
        (it must be the sequencer, and hold no other entry at ``seq``). Raises RaceLost."""
        if leads:
            sequencer = min(set(self.comm.alive) | {self.machine})
            if sequencer != self.machine:
                raise RaceLost(f"satellite {self.machine} is not the sequencer (machine "
                               f"{sequencer} is)")
            other = self._pending_at(seq)
            if other is not None and other != line:
                raise RaceLost(f"log entry {seq} is being committed ({other!r}): another host "
                               "changed the log first")
        if self._pending_at(seq) != line:
            self._set_pending((seq, line))

    def _check(self, req: cmdline.Request, code: bool = True) -> None:
        """Validate a table-changing request against this satellite's tables (kernel thread)
        without importing any code (and, with ``code``, its code reference if the task is this
        satellite's). Raises InstallError saying why it is refused."""
        mgr = self.system.sysmgr
        if isinstance(req, cmdline.Install):
            problem = None
            if code and req.machine == self.machine:
                problem = code_problem(req.code or req.name, self.sf.task_path)
            try:
                mgr.check_install(replace(req, code=FAILED_CODE))
            except InstallError as exc:
                if problem is None:
                    raise
                raise InstallError(f"{exc}\n  - {problem}") from exc
            if problem is not None:
                raise InstallError(f"install {req.name} refused, tables unchanged:\n  - "
                                   f"{problem}")
        elif isinstance(req, cmdline.ResetPri):
            try:
                self.system.msgtab.find(req.src, req.dst)
            except MessageError as exc:
                raise InstallError(f"resetpri: {exc}") from exc
        elif isinstance(req, cmdline.SetPri):
            if req.priority not in PRIORITIES:
                raise InstallError(f"setpri: priority {req.priority} outside {PRIORITY_TEXT}")
            try:
                self.system.msgtab.find(req.src, req.dst)
            except MessageError as exc:
                raise InstallError(f"setpri: {exc}") from exc
