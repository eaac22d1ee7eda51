"""host - the development host (the thesis' Unix side): install, setpri, invoke over the link.

``Host.execute("install -m1i1o1 A2 S3 M2")`` reaches a running multi-satellite system from another
terminal, exactly as the thesis' shell script of section 6.3 does. Table changes are prepared on
every live satellite (each checks them; the target machine also checks the task's code), then
accepted (saved uncommitted) by the sequencer - the lowest-numbered live satellite, a
compare-and-set at the log length every satellite prepared at - and by every other live
satellite, then committed on the sequencer (the commit point) and everywhere else (the protocol
and why the logs cannot diverge: :mod:`chcos.satellites.satellite`). A host that lost the race
to another host prepares again at the new length (up to :data:`RACE_RETRIES` times, then
InstallError); one that finds an accepted, uncommitted entry completes it first. A refused
install changes no satellite's tables.

The answer is what the replicated log holds: a satellite that stops answering during a change
(killed, its link cut) is left out, and the change goes on with the others - it replays the
entry when it rejoins, and the answer says so; when the sequencer stops answering, the host
asks the next one whether the line is in the log (committed, or accepted and then completed)
and carries on from there, so an install is never reported failed while a log holds it, nor
applied twice.
Runtime commands go to the satellite of the task or device concerned. Every request is sealed with
the host role's key of the system secret (see :mod:`chcos.comm.secret`).

Who is up: a satellite's Zenoh liveliness token is only a hint (anyone holding the link's
password can declare one); a machine counts as up once it answered a sealed hello carrying a
nonce the host drew just then (:class:`chcos.satellites.control.HelloRequest`), which only a
satellite of the system, running now, can answer.
"""

from __future__ import annotations

import json
import logging
import random
import secrets
import threading
import time
from typing import Any

from chcos.comm.config import UsrPwdAuth
from chcos.comm.manager import machine_of
from chcos.comm.secret import SystemSecret, Throttle
from chcos.comm.transport import Transport
from chcos.errors import CommandSyntaxError, InstallError, LinkError
from chcos.satellites import control
from chcos.satellites.control import (
    ChangeRequest,
    ControlRequest,
    ExecRequest,
    HeadRequest,
    HelloRequest,
    LogRequest,
    MapRequest,
    Phase,
    SyncRequest,
)
from chcos.satellites.sysfile import SystemFile, link_config_for
from chcos.system import cmdline
from chcos.system.textview import render_text

log = logging.getLogger("chcos.satellites.host")

#: How often a host whose install lost the race to another host prepares it again.
RACE_RETRIES = 50
#: Seconds between two hellos to a machine whose token is seen but which did not answer one.
HELLO_RETRY = 0.5


class RaceLost(InstallError):
    """Another host changed the install log first; the install was not applied."""


class Unreachable(LinkError):
    """A satellite did not answer a request (down, or its link cut): whether it carried the
    request out is not known from here."""


class Host:
    """A host session on the system of ``sf``. ``auth`` (user, password) overrides the
    credentials of the system file or secret (``("", "")``: none at all); ``secret`` overrides
    the system's secret (tests: a process holding another secret). Raises ConfigError for a bad
    system file or secret."""

    def __init__(self, sf: SystemFile, *, auth: tuple[str, str] | None = None,
                 timeout: float = 10.0, settle: float = 3.0,
                 secret: SystemSecret | None = None) -> None:
        secret = secret or sf.secret()
        cfg = link_config_for(sf, None, secret)
        if auth is not None:
            from dataclasses import replace

            cfg = replace(cfg, auth=UsrPwdAuth(*auth, None) if auth[0] else None)
        self.sf = sf
        self.timeout = timeout
        self.settle = settle
        self._settled = False
        self.transport = Transport(cfg, sealer=secret.sealer("host"))
        self.races_lost = 0
        #: liveliness tokens seen without a sealed hello from their machine, by cause
        self.unconfirmed = Throttle(log)
        self._where: dict[str, int] = {}

    def close(self) -> None:
        """Leave the link."""
        self.transport.close()

    def __enter__(self) -> Host:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- who is there -----------------------------------------------------------------------
    def tokens(self) -> list[int]:
        """The machines whose liveliness token is seen now: a hint only (anyone holding the
        link's password can declare one; see :meth:`alive`)."""
        keys = self.transport.alive(f"{self.sf.prefix}/alive/*", timeout=1.0)
        return sorted({m for k in keys if (m := machine_of(k)) is not None})

    def alive(self) -> list[int]:
        """The machines whose satellites are up now: of the machines of the system file whose
        liveliness token is seen, those that answer a sealed hello (see the module doc)."""
        return self._confirmed(set(self.tokens()), self.timeout)

    def _hello(self, machine: int, timeout: float) -> bool:
        """True if satellite ``machine`` answered a hello with a nonce drawn now, sealed by a
        satellite (the transport checks the seal: key, role, freshness, replays); False, and
        counted in :attr:`unconfirmed`, if not (no answer, refused, or a wrong one)."""
        nonce = secrets.token_hex(16)
        try:
            reply = self.transport.request(f"{self.sf.prefix}/m/{machine}/ctl",
                                           control.encode(HelloRequest(nonce)),
                                           timeout=timeout, roles=frozenset({"satellite"}))
            doc = json.loads(reply)
            if (isinstance(doc, dict) and doc.get("ok") is True
                    and doc.get("nonce") == nonce and doc.get("machine") == machine):
                return True
            why = f"answered {str(doc)[:80]!r}, not the hello"
        except LinkError as exc:
            why = str(exc)
        except ValueError as exc:  # not JSON
            why = f"a malformed answer: {exc}"
        self.unconfirmed.note(f"machine {machine}: liveliness token without a sealed hello "
                              f"(not counted as up)", why)
        return False

    def _confirmed(self, hinted: set[int], timeout: float) -> list[int]:
        """The machines of ``hinted`` (token seen) that are of the system file and answer a
        hello within ``timeout`` seconds, asked all at once (sorted)."""
        ask = sorted(m for m in hinted if m in self.sf.satellites)
        for m in sorted(hinted - set(ask)):
            self.unconfirmed.note(f"machine {m}: liveliness token of a machine the system file "
                                  f"does not name (ignored)", f"{self.sf.path}")
        if len(ask) <= 1:
            return [m for m in ask if self._hello(m, timeout)]
        answers: dict[int, bool] = {}

        def hello(m: int) -> None:
            answers[m] = self._hello(m, timeout)

        threads = [threading.Thread(target=hello, args=(m,), name=f"chcos hello m{m}",
                                    daemon=True) for m in ask]
        for t in threads:
            t.start()
        for t in threads:
            t.join()  # each returns within its request's timeout
        return [m for m in ask if answers.get(m)]

    def wait_for(self, machines: list[int], timeout: float = 20.0) -> list[int]:
        """Wait until every machine in ``machines`` is up (its liveliness token is seen, then
        it answers a sealed hello; a machine whose token is seen but which does not answer is
        asked again every :data:`HELLO_RETRY` seconds); returns the machines up then. Raises
        LinkError naming the missing ones after ``timeout`` seconds."""
        want = set(machines)
        hinted: set[int] = set()
        up: set[int] = set()
        lock = threading.Lock()
        changed = threading.Event()

        def seen(key: str, present: bool) -> None:
            m = machine_of(key)
            if m is not None:
                with lock:
                    if present:
                        hinted.add(m)
                    else:
                        hinted.discard(m)
                        up.discard(m)
                changed.set()

        deadline = time.monotonic() + timeout
        with self.transport.watch(f"{self.sf.prefix}/alive/*", lambda k: seen(k, True),
                                  lambda k: seen(k, False)):
            while True:
                changed.clear()
                remaining = deadline - time.monotonic()
                with lock:
                    ask = hinted - up
                if ask and remaining > 0:
                    fresh = self._confirmed(ask, min(self.timeout, remaining))
                    with lock:
                        up.update(m for m in fresh if m in hinted)
                with lock:
                    if want <= up:
                        return sorted(up)
                    missing = sorted(want - up)
                    unanswered = bool(hinted - up)
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                changed.wait(min(remaining, HELLO_RETRY) if unanswered else remaining)
        raise LinkError(f"satellite(s) {missing} of {self.sf.name} not up after {timeout} s "
                        f"(a machine is up once its liveliness token is seen and it answers a "
                        f"sealed hello)")

    # ---- requests ---------------------------------------------------------------------------
    def _ask(self, machine: int, req: ControlRequest) -> dict[str, Any]:
        """Send ``req`` to satellite ``machine`` and return its answer. Raises the refusal as
        CommandSyntaxError, LinkError, RaceLost or InstallError naming the machine, and
        Unreachable if it did not answer."""
        try:
            raw = self.transport.request(f"{self.sf.prefix}/m/{machine}/ctl",
                                         control.encode(req), timeout=self.timeout,
                                         roles=frozenset({"satellite"}))
        except LinkError as exc:
            raise Unreachable(f"machine {machine}: {exc}") from exc
        reply: dict[str, Any] = json.loads(raw)
        if not reply.get("ok"):
            kind = reply.get("type", "")
            err = str(reply.get("error", "refused"))
            if kind == "CommandSyntaxError":
                raise CommandSyntaxError(err)
            if kind == "LinkError":
                raise LinkError(f"machine {machine}: {err}")
            if kind == "RaceLost":
                raise RaceLost(f"machine {machine}: {err}")
            raise InstallError(f"machine {machine}: {err}")
        return reply

    def _map_answer(self, machine: int) -> dict[str, Any]:
        """Satellite ``machine``'s map answer (``map``, ``alive``, ``rejected``), read page by
        page (a large system's map does not fit one link message). Raises LinkError if it
        cannot be read whole (the answer expired three times running), and what :meth:`_ask`
        raises."""
        for _attempt in range(3):
            first = self._ask(machine, MapRequest())
            pages = [str(first["page"])]
            try:
                for part in range(1, int(first["parts"])):
                    pages.append(str(self._ask(machine, MapRequest(part,
                                                                   str(first["token"])))["page"]))
            except LinkError:  # expired while we read (other hosts asked): from the start
                continue
            answer: dict[str, Any] = json.loads("".join(pages))
            return answer
        raise LinkError(f"machine {machine}: the map answer expired three times while read")

    def _up(self) -> list[int]:
        """The machines up. A new session first waits (at most ``timeout``) to reach any, and
        up to ``settle`` seconds more to reach every satellite of the system file."""
        start = time.monotonic()
        up = self.alive()
        want = set(self.sf.satellites)
        while time.monotonic() - start < self.timeout and (
                not up or (not self._settled and set(up) != want
                           and time.monotonic() - start < self.settle)):
            up = self.alive()
        self._settled = True
        if not up:
            raise LinkError(f"no satellite of {self.sf.name} is reachable (not started, or this "
                            "host is not authenticated)")
        return up

    def map_doc(self, machine: int | None = None) -> dict[str, Any]:
        """The system map. With ``machine`` as that satellite sees it; by default merged from
        every satellite up: each task and device as its own machine reports it, each link's
        ``sent`` from its source's machine and ``delivered``/``overwritten``/``status`` from its
        destination's (a command link's status from its caller's mirror). Each device also
        gets ``age``: seconds since its value on its own machine's clock (None before one), and
        ``errors`` lists what each satellite collected (``machine N: ...``)."""
        up = self._up()
        views = {m: self._map_answer(m)["map"]
                 for m in ([machine] if machine is not None else up)}
        doc: dict[str, Any] = dict(views[min(views)])
        where = {t["name"]: t["machine"] for t in doc["tasks"]}
        where.update({d["name"]: d["machine"] for d in doc["devices"]})
        for t in doc["tasks"]:  # terminals and files belong to the machine of their task
            for name in t["inputs"]:
                where.setdefault(name, t["machine"])
        self._where = where
        if machine is None:
            def own(kind: str, item: dict[str, Any]) -> dict[str, Any]:
                view = views.get(where.get(item["name"], -1))
                if view is None:
                    return item
                return next((x for x in view[kind] if x["name"] == item["name"]), item)

            doc["tasks"] = [own("tasks", t) for t in doc["tasks"]]
            doc["devices"] = [own("devices", d) for d in doc["devices"]]
            links = []
            for i, lk in enumerate(doc["links"]):
                merged = dict(lk)
                src_view = views.get(where.get(lk["src"], -1))
                dst_view = views.get(where.get(lk["dst"], -1))
                if src_view is not None:
                    merged["sent"] = src_view["links"][i]["sent"]
                    if lk["type"] == "command":
                        merged["status"] = src_view["links"][i]["status"]
                if dst_view is not None:
                    for key in ("delivered", "overwritten"):
                        merged[key] = dst_view["links"][i][key]
                    if lk["type"] == "sensory":
                        merged["status"] = dst_view["links"][i]["status"]
                links.append(merged)
            doc["links"] = links
        devices = []
        for d in doc["devices"]:  # ages on the clock of the device's own machine
            view = views.get(where.get(d["name"], -1), views[min(views)])
            at = d.get("updated_at")
            devices.append({**d, "age": None if at is None else max(0.0, view["time"] - at)})
        doc["devices"] = devices
        doc["alive"] = up
        # each satellite's collected errors (System.check), named by machine
        doc["errors"] = [f"machine {m}: {e}" for m, v in sorted(views.items())
                         for e in v.get("errors", [])]
        return doc

    def _change(self, line: str, target: int | None) -> str:
        """Put ``line`` in the replicated install log (see the module doc); start again when
        another host got there first or a satellite stopped answering. Returns the answer of
        the task's own satellite (or the sequencer's, saying who replays it later). Raises
        InstallError if it is refused (nothing changed), RaceLost after RACE_RETRIES rounds."""
        tried: set[int] = set()  # log positions where this line was accepted
        for attempt in range(RACE_RETRIES):
            up = self._up() if attempt == 0 else self.alive() or self._up()
            try:
                answer = self._round(line, target, up, tried)
            except (RaceLost, Unreachable) as exc:
                if isinstance(exc, RaceLost):
                    self.races_lost += 1
                    self._sync_sequencer(up)
                else:
                    log.info("install %r: %s; asking the satellites up again", line, exc)
                time.sleep(random.uniform(0.0, 0.02 * (attempt + 1)))  # back off, then retry
                continue
            if answer is not None:
                return answer
        raise RaceLost(f"{line!r} not applied: other hosts changed the install log first "
                       f"{RACE_RETRIES} times in a row")

    def _round(self, line: str, target: int | None, up: list[int],
               tried: set[int]) -> str | None:
        """One attempt: the answer once ``line`` is committed, None if the round committed
        another host's accepted entry first (try again). Raises RaceLost, Unreachable (the
        sequencer did not answer), InstallError (refused)."""
        leader = min(up)
        head = self._ask(leader, HeadRequest())
        seq = int(head["length"])
        if any(s < seq for s in tried):  # an earlier attempt may have been committed
            held = self._ask(leader, LogRequest())["log"]
            if any(s < len(held) and held[s] == line for s in tried):
                return f"{line}: committed (the sequencer stopped answering meanwhile)"
        if head.get("pending") is not None:
            value = str(head["pending"])
            answers = self._complete(value, seq, up, leader, tried if value == line else None)
            return self._answer(answers, target, up) if value == line else None
        order = sorted(up, key=lambda m: (m != target, m))
        live, pending = [], {}
        for m in order:
            try:
                reply = self._ask(m, ChangeRequest(Phase.PREPARE, line, seq, leader))
            except Unreachable:
                if m == leader:
                    raise
                continue  # down: it catches up when it rejoins
            live.append(m)
            if reply.get("pending") is not None:
                pending[m] = str(reply["pending"])
        value = pending[min(pending)] if pending else line
        answers = self._complete(value, seq, live, leader, tried if value == line else None)
        return self._answer(answers, target, up) if value == line else None

    def _complete(self, value: str, seq: int, live: list[int], leader: int,
                  tried: set[int] | None) -> dict[int, str]:
        """Accept ``value`` as entry ``seq`` on the sequencer then on the others of ``live``,
        commit it on the sequencer (the commit point) then on the others; a follower that does
        not answer is left out (it replays the entry when it rejoins). Returns the answers of
        the satellites that committed it. Raises RaceLost, Unreachable (the sequencer)."""
        self._ask(leader, ChangeRequest(Phase.ACCEPT, value, seq, leader))
        if tried is not None:
            tried.add(seq)
        accepted = [leader]
        for m in live:
            if m != leader:
                try:
                    self._ask(m, ChangeRequest(Phase.ACCEPT, value, seq, leader))
                    accepted.append(m)
                except Unreachable:
                    continue
        answers = {leader: str(self._ask(leader, ChangeRequest(Phase.COMMIT, value, seq,
                                                               leader))["answer"])}
        for m in accepted[1:]:
            try:
                answers[m] = str(self._ask(m, ChangeRequest(Phase.COMMIT, value, seq,
                                                            leader))["answer"])
            except Unreachable:
                continue
        return answers

    def _answer(self, answers: dict[int, str], target: int | None, up: list[int]) -> str:
        """The answer of the task's own satellite, or the sequencer's saying which satellites
        replay the committed entry when they rejoin."""
        if target in answers:
            return answers[target]
        later = sorted(m for m in self.sf.satellites
                       if m not in answers and (m in up or m == target))
        text = answers[min(answers)]
        if later:
            text += (f" (committed on machine(s) {sorted(answers)}; machine(s) {later} did not "
                     "answer and apply it when they rejoin)")
        return text

    def _sync_sequencer(self, up: list[int]) -> None:
        """If the sequencer holds fewer log entries than another satellite (it restarted alone
        and reloaded an older map), have it fetch the missing ones from the longest log."""
        try:
            lengths = {m: int(self._ask(m, HeadRequest())["length"]) for m in up}
            longest = max(lengths, key=lambda m: (lengths[m], -m))
            leader = min(up)
            if lengths[leader] < lengths[longest]:
                self._ask(leader, SyncRequest(longest, lengths[longest]))
        except (InstallError, LinkError):
            pass  # the next attempt finds out again

    def rejected(self, machine: int) -> dict[str, int]:
        """How many payloads satellite ``machine`` refused so far, by cause."""
        return dict(self._map_answer(machine)["rejected"])

    def log_heads(self) -> dict[int, tuple[int, str]]:
        """(length, SHA-256) of the install log of every satellite up."""
        out = {}
        for m in self._up():
            head = self._ask(m, HeadRequest())
            out[m] = (int(head["length"]), str(head["hash"]))
        return out

    def execute(self, line: str) -> str:
        """Carry out one host command line on the system; returns the answer. Raises
        CommandSyntaxError, InstallError (nothing changed anywhere), LinkError. A line longer
        than a satellite takes (``control.MAX_LINE``) is refused here, before it is sent."""
        if len(line) > control.MAX_LINE:
            raise CommandSyntaxError(f"{line[:40].strip()}...: a command line of {len(line)} "
                                     f"characters; a satellite takes at most "
                                     f"{control.MAX_LINE}")
        req = cmdline.parse(line)
        if req is None:
            return ""
        if isinstance(req, cmdline.ShowMap):
            return render_text(self.map_doc())
        if isinstance(req, cmdline.Install | cmdline.SetPri | cmdline.ResetPri | cmdline.Boot):
            return self._change(line, getattr(req, "machine", None))
        up = self._up()
        if isinstance(req, cmdline.TaskOp) and req.op == "reset" and not req.task:
            return "; ".join(f"machine {m}: {self._ask(m, ExecRequest(line))['answer']}"
                             for m in up)
        name = (req.task if isinstance(req, cmdline.Invoke | cmdline.TaskOp)
                else req.device if isinstance(req, cmdline.Inject | cmdline.AxisCmd) else "")
        if name not in self._where:
            self.map_doc()
        machine = self._where.get(name)
        if machine is None:
            raise InstallError(f"no task or device named {name!r} in {self.sf.name}")
        if machine not in up:
            raise LinkError(f"{name} runs on machine {machine}, which is not up")
        return str(self._ask(machine, ExecRequest(line))["answer"])
