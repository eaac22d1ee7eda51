"""satellite - one machine of a CHC-OS system, in its own process, on the Zenoh link.

A satellite runs the kernel, tasks and devices of its machine and keeps a copy of the whole system
tables, which every satellite builds from the same *install log*: the host's install, setpri and
boot commands in the order the host committed them (thesis 6: "every processor keeps the same
message table, updated by broadcast at each install"). A host command that changes the tables goes
in two phases: ``prepare`` (every live satellite checks it against its tables, and the task's own
satellite also loads its code) and ``commit`` (every live satellite applies it as log entry number
``seq``). A satellite that starts late or restarts fetches the log from any live one before it runs
anything; with nobody up it reloads its own sysfile.map. Runtime commands (invoke, suspend,
resume, close, inject) go only to the satellite that runs the task or device.

Control keys, under ``chcos/<system>``: ``m/<N>/ctl`` (host requests to machine N, JSON) and
``log`` (any satellite answers with the install log).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from typing import Any

from chcos import cmdline, sysmap
from chcos.clock import Clock, RealClock
from chcos.comm import CommManager
from chcos.errors import ChcosError, ConfigError, InstallError, LinkError, MessageError
from chcos.link.transport import Subscription, Transport
from chcos.sysfile import SystemFile, link_config_for
from chcos.system import System

log = logging.getLogger("chcos.satellite")

MUTATING = (cmdline.Install, cmdline.SetPri, cmdline.ResetPri, cmdline.Boot)
#: How long a starting satellite keeps asking for the install log before it concludes that it is
#: alone (links to the other satellites are made in the background, within milliseconds).
CATCH_UP_WAIT = 2.0


class Satellite:
    """Machine ``machine`` of the system described by ``sf``. Raises ConfigError if the
    system file has no such machine, LinkError if its port cannot be opened."""

    def __init__(self, sf: SystemFile, machine: int, *, clock: Clock | None = None) -> None:
        if machine not in sf.satellites:
            raise ConfigError(f"{sf.path}: no [[satellite]] with machine = {machine}")
        self.sf = sf
        self.machine = machine
        self.system = System(sf.devmaps, clock=clock or RealClock(), task_path=sf.task_path,
                             base_dir=sf.base_dir, map_path=sf.map_path(machine),
                             local_machines={machine})
        self.transport = Transport(link_config_for(sf, machine))
        self.comm = CommManager(self.system, self.transport, sf.prefix, machine)
        self.log: list[str] = []
        self._lock = threading.RLock()
        self._subs: list[Subscription] = []
        self._stopping = threading.Event()
        self.refused: list[str] = []

    # ---- life -------------------------------------------------------------------------------
    def start(self) -> None:
        """Run the kernel, join the link, catch up with the install log, then serve the host."""
        self.system.start()
        self.comm.start()
        self.catch_up()
        p = self.sf.prefix
        self._subs.append(self.transport.serve(f"{p}/m/{self.machine}/ctl", self._control))
        self._subs.append(self.transport.serve(f"{p}/log", lambda _: self._log_bytes()))
        self.comm.announce()
        log.info("satellite %d of %s up, %d log entries", self.machine, self.sf.name,
                 len(self.log))

    def stop(self) -> None:
        """Leave the link, stop the kernel, put actuators safe, stop the drivers."""
        self._stopping.set()
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

    # ---- the install log ----------------------------------------------------------------------
    def _log_bytes(self) -> bytes:
        with self._lock:
            return json.dumps(self.log).encode()

    def catch_up(self) -> int:
        """Apply the log entries this satellite misses, fetched from any live satellite; with
        none up, replay its own sysfile.map. Returns how many entries were applied."""
        entries = None
        deadline = time.monotonic() + CATCH_UP_WAIT
        while entries is None:  # links to peers come up in the background: give them a moment
            try:
                entries = json.loads(self.transport.request(f"{self.sf.prefix}/log", b"",
                                                            timeout=1.5))
            except LinkError:
                if time.monotonic() >= deadline:
                    break
                self._stopping.wait(0.05)  # retry back-off
        with self._lock:
            if entries is None:
                path = self.sf.map_path(self.machine)
                if not self.log and path.exists():
                    entries = sysmap.install_lines(sysmap.read(path))
                    log.info("no satellite answered: reloading %s", path)
                else:
                    return 0
            n = 0
            for line in entries[len(self.log):]:
                self._apply(line)
                n += 1
            return n

    def _apply(self, line: str) -> str:
        answer = self.system.execute(line)
        self.log.append(line)
        return answer

    # ---- host requests ----------------------------------------------------------------------
    def _control(self, payload: bytes) -> bytes:
        try:
            req = json.loads(payload)
            reply = self._serve(req)
        except ChcosError as exc:
            text = str(exc)
            self.refused.append(text)
            log.warning("satellite %d refused a host request: %s", self.machine, text)
            reply = {"ok": False, "error": text, "type": type(exc).__name__}
        except (ValueError, KeyError, TypeError) as exc:
            text = f"malformed host request: {type(exc).__name__}: {exc}"
            self.refused.append(text)
            log.warning("satellite %d: %s", self.machine, text)
            reply = {"ok": False, "error": text, "type": "LinkError"}
        return json.dumps(reply, default=str).encode()

    def _serve(self, req: dict[str, Any]) -> dict[str, Any]:
        op = req["op"]
        if op == "map":
            doc = self.system.call(self.system.sysmgr.map_doc)
            return {"ok": True, "map": doc, "alive": sorted(self.comm.alive)}
        if op == "log":
            return {"ok": True, "log": json.loads(self._log_bytes())}
        line = str(req["line"])
        parsed = cmdline.parse(line)
        if parsed is None:
            return {"ok": True, "answer": ""}
        if op == "exec":
            if isinstance(parsed, MUTATING):
                raise InstallError(f"{line!r} changes the tables: it must be prepared and "
                                   "committed on every satellite")
            return {"ok": True, "answer": self.system.execute(parsed)}
        seq = int(req["seq"])
        with self._lock:
            if seq > len(self.log):
                self.catch_up()
            if op == "prepare":
                if seq != len(self.log):
                    raise InstallError(f"satellite {self.machine} has {len(self.log)} log "
                                       f"entries, the host expected {seq}")
                self.system.call(self._check, parsed)
                return {"ok": True, "seq": seq}
            if op == "commit":
                if seq < len(self.log):
                    return {"ok": True, "answer": "already applied", "seq": seq}
                if seq != len(self.log):
                    raise InstallError(f"satellite {self.machine} cannot apply log entry {seq}: "
                                       f"it has {len(self.log)}")
                return {"ok": True, "answer": self._apply(line), "seq": seq}
        raise MessageError(f"unknown host request op {op!r}")

    def _check(self, req: cmdline.Request) -> None:
        """Validate a table-changing request against this satellite's tables (kernel thread)."""
        mgr = self.system.sysmgr
        if isinstance(req, cmdline.Install):
            mgr.check_install(req)
        elif isinstance(req, cmdline.ResetPri):
            try:
                self.system.msgtab.find(req.src, req.dst)
            except MessageError as exc:
                raise InstallError(f"resetpri: {exc}") from exc
        elif isinstance(req, cmdline.SetPri):
            if not 0 <= req.priority <= 99:
                raise InstallError(f"setpri: priority {req.priority} outside 0..99")
            try:
                self.system.msgtab.find(req.src, req.dst)
            except MessageError as exc:
                raise InstallError(f"setpri: {exc}") from exc
