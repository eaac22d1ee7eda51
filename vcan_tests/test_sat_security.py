"""Satellites secure by default (issue 19): each attack tried against running satellites on
loopback is refused. A process without the system's secret cannot reach a satellite at all; a
process that holds it but seals with the wrong role cannot act as the host or as a satellite;
code named by an install is never imported from an arbitrary path (and never before commit);
junk is counted and logged once per cause; the install log of a starting satellite is validated;
run state lives in the system's own state directory; the system file refuses exposed satellites."""

from __future__ import annotations

import json
import os
import shutil
import stat
import threading
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from chcos.comm.codec import LinkMessage, MessageKind, encode, encode_batch
from chcos.comm.secret import load_or_create
from chcos.comm.transport import Transport
from chcos.errors import ConfigError, InstallError, LinkError
from chcos.satellites import sysfile
from chcos.satellites.control import ChangeRequest, Phase
from chcos.satellites.host import Host
from chcos.satellites.satellite import Satellite
from drivers.memory import HISTORY_BYTES, ActuatorStore
from vcan_tests.netutil import free_port
from vcan_tests.support_sat import Cluster, device

S = "vcan_tests.support_sat"


def _sysfile(tmp: Path, body: str = "", name: str = "sec", sats: str = "") -> Path:
    path = tmp / "system.toml"
    sats = sats or f"[[satellite]]\nmachine = 0\nport = {free_port()}\n"
    path.write_text(f'[system]\nname = "{name}"\nstate_dir = "state"\n\n{sats}\n{body}')
    return path


# ---- the system file and the secret -------------------------------------------------------------

def test_secret_is_generated_owner_only_in_the_system_state_dir(tmp_path: Path) -> None:
    sf = sysfile.load(_sysfile(tmp_path))
    secret = sf.secret()
    assert secret.path == tmp_path / "state" / "sec" / "secret.json"
    assert stat.S_IMODE(secret.path.stat().st_mode) == 0o600
    assert stat.S_IMODE(secret.path.parent.stat().st_mode) == 0o700
    users = secret.dictionary()
    assert stat.S_IMODE(users.stat().st_mode) == 0o600
    assert sorted(line.split(":")[0] for line in users.read_text().splitlines()) == [
        "host", "satellite"]
    assert sf.secret().keys == secret.keys  # generated once, then read
    assert "keys" not in repr(secret) and secret.keys["host"].hex() not in repr(secret)
    os.chmod(secret.path, 0o644)
    with pytest.raises(ConfigError, match="chmod 600"):
        sf.secret()
    os.chmod(secret.path, 0o600)
    with pytest.raises(ConfigError, match="not of 'other'"):
        load_or_create(secret.path, "other")


def test_a_loopback_system_talks_mutual_tls_with_certificates_of_its_own(tmp_path: Path) -> None:
    if shutil.which("openssl") is None:
        pytest.fail("the openssl tool is needed (Debian: openssl)")
    sf = sysfile.load(_sysfile(tmp_path))
    cfg = sysfile.link_config_for(sf, 0, sf.secret())
    assert cfg.listen_endpoints[0].startswith("tls/127.0.0.1:")
    assert cfg.tls is not None and cfg.tls.enable_mtls and cfg.tls.verify_name_on_connect
    assert cfg.auth is not None and cfg.auth.user == "satellite"
    tls = tmp_path / "state" / "sec" / "tls"
    assert sorted(f.name for f in tls.iterdir()) == ["ca.pem", "node.key", "node.pem"]
    assert all(stat.S_IMODE(f.stat().st_mode) == 0o600 for f in tls.iterdir())
    assert cfg.tls.root_ca_certificate == tls / "ca.pem"  # its key is gone: nothing else signed
    host_cfg = sysfile.link_config_for(sf, None, sf.secret())
    assert host_cfg.connect_endpoints[0].startswith("tls/") and host_cfg.auth is not None
    assert host_cfg.auth.user == "host"


def test_non_loopback_satellite_without_tls_is_refused_saying_what_to_add(tmp_path: Path) -> None:
    sats = ("[[satellite]]\nmachine = 0\nport = 7447\nhost = \"10.99.0.2\"\n"
            "[[satellite]]\nmachine = 1\nport = 7447\nhost = \"10.99.0.3\"\n")
    with pytest.raises(ConfigError, match=r"10\.99\.0\.2.*not a loopback address: add a "
                                          r"\[link\.tls\].*enable_mtls = true"):
        sysfile.load(_sysfile(tmp_path, sats=sats))
    for f in ("ca.pem", "cert.pem", "key.pem"):
        (tmp_path / f).write_text("x")
    tls = ('[link.tls]\nroot_ca_certificate = "ca.pem"\nlisten_certificate = "cert.pem"\n'
           'listen_private_key = "key.pem"\nconnect_certificate = "cert.pem"\n'
           'connect_private_key = "key.pem"\n')
    with pytest.raises(ConfigError, match="peers are not authenticated: set enable_mtls"):
        sysfile.load(_sysfile(tmp_path, tls, sats=sats))
    sf = sysfile.load(_sysfile(tmp_path, tls + "enable_mtls = true\n", sats=sats))
    cfg = sysfile.link_config_for(sf, 0)
    assert cfg.listen_endpoints == ["tls/10.99.0.2:7447"]
    assert cfg.connect_endpoints == []  # the higher-numbered satellites connect to it
    assert sysfile.link_config_for(sf, 1).connect_endpoints == ["tls/10.99.0.2:7447"]
    assert sysfile.link_config_for(sf, None).connect_endpoints == [
        "tls/10.99.0.2:7447", "tls/10.99.0.3:7447"]
    v6 = sats.replace("10.99.0.2", "fd00::2")
    sf = sysfile.load(_sysfile(tmp_path, tls + "enable_mtls = true\n", sats=v6))
    assert sysfile.link_config_for(sf, 1).connect_endpoints == ["tls/[fd00::2]:7447"]
    for bad in ("0.0.0.0", "::", "224.0.0.224", "not a host"):
        with pytest.raises(ConfigError, match=r"satellite\[0\]\.host"):
            sysfile.load(_sysfile(tmp_path, sats=sats.replace("10.99.0.2", bad)))


def test_chcos_check_system_refuses_an_exposed_satellite(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from chcos.cli.main import main

    ok = _sysfile(tmp_path)
    assert main(["check", "--system", str(ok)]) == 0
    assert "peers authenticated by the system secret" in capsys.readouterr().out
    exposed = tmp_path / "exposed.toml"
    exposed.write_text(ok.read_text().replace("port =", 'host = "192.0.2.7"\nport ='))
    assert main(["check", "--system", str(exposed)]) == 1
    assert "192.0.2.7 is not a loopback address: add a [link.tls]" in capsys.readouterr().err


def test_auth_without_dictionary_is_refused_at_load(tmp_path: Path) -> None:
    body = '[link.auth]\nuser = "sat"\npassword = "pw"\n'
    with pytest.raises(ConfigError, match=r"link\.auth\.dictionary_file: missing"):
        sysfile.load(_sysfile(tmp_path, body))


def test_run_state_belongs_to_one_system(tmp_path: Path) -> None:
    a = sysfile.load(_sysfile(tmp_path, name="alpha"))
    (tmp_path / "b").mkdir()
    b_path = _sysfile(tmp_path / "b", name="beta")
    b_path.write_text(b_path.read_text().replace('state_dir = "state"',
                                                 f'state_dir = "{tmp_path / "state"}"'))
    b = sysfile.load(b_path)
    assert a.map_path(0) == tmp_path / "state" / "alpha" / "m0.map"
    assert b.map_path(0) == tmp_path / "state" / "beta" / "m0.map"
    assert a.secret().keys != b.secret().keys
    # the default is outside the system file's directory (never the task sources)
    plain = tmp_path / "plain.toml"
    plain.write_text(f'[system]\nname = "p"\n[[satellite]]\nmachine = 0\nport = {free_port()}\n')
    before = os.environ.get("CHCOS_STATE_DIR")
    os.environ["CHCOS_STATE_DIR"] = str(tmp_path / "elsewhere")
    try:
        assert sysfile.load(plain).map_path(0) == tmp_path / "elsewhere" / "p" / "m0.map"
    finally:
        if before is None:
            del os.environ["CHCOS_STATE_DIR"]
        else:
            os.environ["CHCOS_STATE_DIR"] = before


def test_another_system_with_the_same_base_dir_does_not_adopt_the_tables(tmp_path: Path) -> None:
    (tmp_path / "devices.toml").write_text("")
    for name in ("first", "second"):
        path = _sysfile(tmp_path, name=name)
        sf = sysfile.load(path)
        with Satellite(sf, 0) as sat:
            sat.start()
            if name == "first":
                with Host(sf, timeout=10.0) as host:
                    host.wait_for([0])
                    host.execute("install -m0 sysfile")
                    host.execute(f"install -m0 --code={S}:worker W")
                assert len(sat.log) == 2
            else:
                assert sat.log == []  # nothing adopted from "first"
    assert not list(tmp_path.glob("*.map"))  # nothing beside the system file


# ---- attacks on running satellites -----------------------------------------------------------

@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    c = Cluster(tmp_path, machines=(0, 1))
    c.start(0)
    c.start(1)
    c.host.wait_for([0, 1])
    for line in ("install -m0 sysfile", "install -m1 sysfile",
                 f"install -m0i1o1 --code={S}:relay R0 S0 M0"):
        c.host.execute(line)
    yield c
    c.close()


def _member(c: Cluster, role: str) -> Transport:
    """A process holding the system's secret, sealing with ``role``, once it sees every
    satellite (so that what it publishes has somewhere to go)."""
    secret = c.sf.secret()
    t = Transport(sysfile.link_config_for(c.sf, None, secret), sealer=secret.sealer(role))
    seen: set[str] = set()
    cond = threading.Condition()

    def joined(key: str) -> None:
        with cond:
            seen.add(key)
            cond.notify_all()

    t.watch(f"{c.sf.prefix}/alive/*", joined, lambda _k: None)
    with cond:
        assert cond.wait_for(lambda: len(seen) == len(c.procs), timeout=20)
    return t


def _wait_rejected(c: Cluster, machine: int, cause: str, n: int = 1) -> dict[str, int]:
    def seen(_doc: object) -> bool:
        return sum(v for k, v in c.host.rejected(machine).items() if cause in k) >= n
    c.wait_until(seen)
    return c.host.rejected(machine)


@pytest.mark.slow
def test_a_process_without_the_secret_reaches_nothing(cluster: Cluster) -> None:
    # built exactly as chcos builds its own configuration, but without the system's secret
    rogue = Transport(sysfile.link_config_for(cluster.sf, None))
    try:
        assert rogue.alive(f"{cluster.sf.prefix}/alive/*", timeout=1.0) == []  # reads nothing
        with pytest.raises(LinkError):
            rogue.request(f"{cluster.sf.prefix}/m/0/ctl",
                          json.dumps({"op": "exec", "line": "inject S0 777"}).encode(),
                          timeout=1.0)
        estop = encode(LinkMessage(MessageKind.COMMAND, "", "", 0, 99, 1, 0,
                                   {"op": "estop", "reason": "rogue", "from": 7}))
        rogue.publish(f"{cluster.sf.prefix}/all/msg", encode_batch([estop]), priority=99,
                      kind=MessageKind.COMMAND)
        assert rogue.peers() == []  # no satellite let it in: nothing it sent arrived
    finally:
        rogue.close()
    doc = cluster.host.map_doc()
    assert device(doc, "S0")["value"] is None and device(doc, "M0")["status"] == "OK"
    assert device(doc, "M0")["value"] is None  # no e-stop wrote its safe value


@pytest.mark.slow
def test_only_the_host_role_controls_and_only_satellites_send_messages(cluster: Cluster) -> None:
    p = cluster.sf.prefix
    sat = _member(cluster, "satellite")
    host = _member(cluster, "host")
    try:
        # a satellite-sealed host request (install, inject...) is refused before it is read
        for req in ({"op": "exec", "line": "inject S0 777"},
                    {"op": "prepare", "line": f"install -m0 --code={S}:worker X", "seq": 3}):
            with pytest.raises(LinkError, match="not authorised"):
                sat.request(f"{p}/m/0/ctl", json.dumps(req).encode(), timeout=5.0)
        # host-sealed satellite traffic: e-stop, forged status, actuator write
        for value in ({"op": "estop", "reason": "forged", "from": 1},
                      {"op": "actuator", "device": "M0", "value": 55}):
            msg = encode(LinkMessage(MessageKind.COMMAND, "", "", 0, 98, 1, 0, value))
            host.publish(f"{p}/m/0/msg", encode_batch([msg]), priority=98,
                         kind=MessageKind.COMMAND)
        status = encode(LinkMessage(MessageKind.STATUS, "", "S0", 0, 98, 1, 0,
                                    {"device": "S0", "status": "failed", "reason": "forged",
                                     "from": 1}))
        host.publish(f"{p}/all/msg", encode_batch([status]), priority=98,
                     kind=MessageKind.STATUS)
        counts = _wait_rejected(cluster, 0, "payload from a host refused", 3)
        assert sum(v for k, v in counts.items() if "from a satellite refused" in k) == 2
    finally:
        sat.close()
        host.close()
    doc = cluster.host.map_doc()
    assert device(doc, "S0")["status"] == "OK" and device(doc, "S0")["value"] is None
    assert device(doc, "M0")["status"] == "OK" and device(doc, "M0")["value"] is None
    assert [t["name"] for t in doc["tasks"]] == ["R0"]


@pytest.mark.slow
def test_actuator_values_are_type_checked_at_the_link(cluster: Cluster) -> None:
    p = cluster.sf.prefix
    sat = _member(cluster, "satellite")
    try:
        for value in ("a string", [1, 2], True, 3.5):
            msg = encode(LinkMessage(MessageKind.COMMAND, "R9", "M0", 0, 98, 1, 0,
                                     {"op": "actuator", "device": "M0", "value": value}))
            sat.publish(f"{p}/m/0/msg", encode_batch([msg]), priority=98,
                        kind=MessageKind.COMMAND)
        doc = cluster.wait_until(lambda d: device(d, "M0")["value"] == 3.5)
        counts = cluster.host.rejected(0)
        assert sum(v for k, v in counts.items() if "refused (COMMAND" in k) == 3
        assert device(doc, "M0")["commands"] == 1
    finally:
        sat.close()


@pytest.mark.slow
def test_install_code_outside_the_task_path_is_never_imported(cluster: Cluster,
                                                              tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    evil = tmp_path / "evil.py"
    evil.write_text(f"open({str(marker)!r}, 'w').write('ran')\n"
                    "async def main(ctx, cmd):\n    pass\n")
    with pytest.raises(InstallError, match="outside the system's task path"):
        cluster.host.execute(f"install -m0 --code={evil}:main EVIL")
    # the same request sent as a bare prepare (no commit) by the host role
    with pytest.raises(InstallError, match="outside the system's task path"):
        cluster.host._ask(0, ChangeRequest(Phase.PREPARE,
                                           f"install -m0 --code={evil}:main EVIL", 3))
    assert not marker.exists()
    assert "EVIL" not in [t["name"] for t in cluster.host.map_doc()["tasks"]]


@pytest.mark.slow
def test_junk_is_counted_and_logged_once_per_cause(cluster: Cluster) -> None:
    p = cluster.sf.prefix
    sat = _member(cluster, "satellite")
    n = 3000
    try:
        for i in range(n):
            sat.publish(f"{p}/m/0/msg", b"junk %d" % i, priority=10, kind=MessageKind.COMMAND)
        counts = _wait_rejected(cluster, 0, "malformed", n)
    finally:
        sat.close()
    assert counts["incoming batch refused (malformed)"] == n
    text = (cluster.tmp / "sat0.log").read_text()
    assert text.count("incoming batch refused (malformed)") <= 2
    assert "Traceback" not in text


def test_oversized_payloads_are_refused_at_the_link(tmp_path: Path) -> None:
    secret = load_or_create(tmp_path / "s.json", "t")
    port = free_port()
    from chcos.comm import LinkConfig

    with Transport(LinkConfig(port), sealer=secret.sealer("satellite"),
                   max_bytes=1000) as small, \
            Transport(LinkConfig(None, (port,)), sealer=secret.sealer("satellite")) as big:
        with pytest.raises(LinkError, match="larger than the link's limit"):
            small.publish("t/x", b"x" * 1001, priority=10, kind=MessageKind.COMMAND)
        got: list[bytes] = []
        done = threading.Event()

        def on(_k: str, payload: bytes) -> None:
            got.append(payload)
            done.set()

        small.subscribe("t/x", on)
        small.announce("t/alive")
        joined = threading.Event()
        big.watch("t/alive", lambda _k: joined.set(), lambda _k: None)
        assert joined.wait(10)
        big.publish("t/x", b"y" * 5000, priority=10, kind=MessageKind.COMMAND)
        big.publish("t/x", b"ok", priority=10, kind=MessageKind.COMMAND)  # same order, after
        assert done.wait(10)
        assert got == [b"ok"]
        assert small.rejected.counts == {"link subscriber t/x: oversized payload dropped": 1}


def test_memory_bus_history_is_bounded_in_bytes() -> None:
    store = ActuatorStore(["M"], history=200)
    for i in range(20):
        store.put("M", str(i) * (8 * 1024 * 1024))
    assert len(store.history("M")) == 1 and store.count("M") == 20
    for i in range(50):
        store.put("M", i)
    assert store.history("M") == list(range(50))
    assert sum(len(str(v)) for v in store.history("M")) < HISTORY_BYTES


def test_a_rogue_log_answer_does_not_crash_a_starting_satellite(tmp_path: Path) -> None:
    (tmp_path / "devices.toml").write_text("")
    sats = "".join(f"[[satellite]]\nmachine = {m}\nport = {free_port()}\n" for m in (0, 1))
    sf = sysfile.load(_sysfile(tmp_path, sats=sats))
    secret = sf.secret()
    # a member (it holds the secret) that answers the log with junk, listening as machine 1
    rogue = Transport(sysfile.link_config_for(sf, 1, secret), sealer=secret.sealer("satellite"))
    try:
        rogue.serve(f"{sf.prefix}/log", lambda _p: json.dumps({"not": "a list"}).encode())
        with Satellite(sf, 0) as sat:
            sat.start()
            assert sat.log == []
            assert sat.rejected.counts["install log refused"] >= 1
        bad_entries = json.dumps(["install -m0 sysfile", "invoke R0"]).encode()
        rogue2 = rogue.serve(f"{sf.prefix}/m/1/log", lambda _p: bad_entries)
        with Satellite(sf, 0) as sat:
            with pytest.raises(LinkError, match="could not fetch"):
                sat.catch_up(source=1, need=1)  # entry 1 is no install: the whole log refused
            assert sat.log == [] and sat.rejected.counts["install log refused"] >= 1
        rogue2.close()
    finally:
        rogue.close()
    # a well-formed log, but served by the host role: only satellites' logs are taken
    forged = json.dumps(["install -m0 sysfile", f"install -m0 --code={S}:worker FAKE"]).encode()
    rogue = Transport(sysfile.link_config_for(sf, 1, secret), sealer=secret.sealer("host"))
    try:
        rogue.serve(f"{sf.prefix}/log", lambda _p: forged)
        with Satellite(sf, 0) as sat:
            sat.start()
            assert sat.log == []
            assert sat.transport.rejected.counts[
                f"link request {sf.prefix}/log: payload from a host refused"] >= 1
    finally:
        rogue.close()


def test_commit_below_the_log_length_compares_the_line(tmp_path: Path) -> None:
    (tmp_path / "devices.toml").write_text("")
    sf = sysfile.load(_sysfile(tmp_path))
    sf = replace(sf, devmaps=())
    with Satellite(sf, 0) as sat:
        sat.start()
        with Host(sf, timeout=10.0) as host:
            host.wait_for([0])
            host.execute("install -m0 sysfile")
            assert host._ask(0, ChangeRequest(Phase.COMMIT, "install -m0 sysfile",
                                              0))["answer"] == "already applied"
            with pytest.raises(InstallError, match="diverged"):
                host._ask(0, ChangeRequest(Phase.COMMIT, f"install -m0 --code={S}:worker W",
                                           0))
            assert sat.log == ["install -m0 sysfile"]


def _two(tmp_path: Path) -> sysfile.SystemFile:
    sats = "".join(f"[[satellite]]\nmachine = {m}\nport = {free_port()}\n" for m in (0, 1))
    return sysfile.load(_sysfile(tmp_path, sats=sats))


def _install(sf: sysfile.SystemFile, up: list[int], *lines: str) -> Host:
    host = Host(sf, timeout=10.0, settle=0.5)
    host.wait_for(up)
    for line in lines:
        host.execute(line)
    return host


@pytest.mark.slow
def test_a_stale_sequencer_is_brought_up_to_date(tmp_path: Path) -> None:
    sf = _two(tmp_path)
    boots = ("install -m0 sysfile", "install -m1 sysfile")
    with Satellite(sf, 0) as s0, Satellite(sf, 1) as s1:
        s0.start()
        s1.start()
        _install(sf, [0, 1], *boots).close()
        s0.stop()
        _install(sf, [1], f"install -m1 --code={S}:worker W").close()
    with Satellite(sf, 0) as s0:  # alone: replays its own (older) log
        s0.start()
        assert s0.log == list(boots)
        with Satellite(sf, 1) as s1:  # its saved log extends the sequencer's: keeps its own
            s1.start()
            assert len(s1.log) == 3
            host = _install(sf, [0, 1], f"install -m0 --code={S}:worker Z")
            assert host.races_lost >= 1  # the sequencer was behind, then synced
            assert s0.log == s1.log and s0.log[2:] == [f"install -m1 --code={S}:worker W",
                                                        f"install -m0 --code={S}:worker Z"]
            host.close()


@pytest.mark.slow
def test_a_satellite_whose_log_contradicts_its_peers_refuses_to_start(tmp_path: Path) -> None:
    sf = _two(tmp_path)
    with Satellite(sf, 0) as s0, Satellite(sf, 1) as s1:
        s0.start()
        s1.start()
        _install(sf, [0, 1], "install -m0 sysfile", "install -m1 sysfile").close()
        s1.stop()
        _install(sf, [0], f"install -m0 --code={S}:worker X").close()  # only 0 has entry 2
    with Satellite(sf, 1) as s1:  # alone (a partition): entry 2 becomes something else
        s1.start()
        _install(sf, [1], f"install -m1 --code={S}:worker Y").close()
        with Satellite(sf, 0) as s0, pytest.raises(LinkError, match="differs from this "
                                                   "satellite's at entry 2"):
            s0.start()


def test_code_that_fails_to_load_after_commit_keeps_the_tables_alike(tmp_path: Path) -> None:
    (tmp_path / "tasks").mkdir()
    (tmp_path / "tasks" / "BROKEN.py").write_text("raise RuntimeError('no such hardware')\n")
    path = _sysfile(tmp_path)
    path.write_text(path.read_text().replace('state_dir = "state"',
                                             'state_dir = "state"\ntask_path = ["tasks"]'))
    sf = sysfile.load(path)
    with Satellite(sf, 0) as sat:
        sat.start()
        with Host(sf, timeout=10.0) as host:
            host.wait_for([0])
            host.execute("install -m0 sysfile")
            answer = host.execute("install -m0 BROKEN")
            assert "BROKEN entered in the tables, but its code failed to load" in answer
            assert "no such hardware" in answer
            assert [t["name"] for t in host.map_doc()["tasks"]] == ["BROKEN"]
            assert sat.log[-1] == "install -m0 BROKEN"
            host.execute("invoke BROKEN")
            deadline = time.monotonic() + 20
            doc = host.map_doc()
            while not doc["tasks"][0]["last_error"] and time.monotonic() < deadline:
                doc = host.map_doc()  # each poll is a round trip
            assert "no such hardware" in doc["tasks"][0]["last_error"]


def test_install_logs_are_owner_only(tmp_path: Path) -> None:
    from chcos.satellites.installlog import append_log, read_log, write_log

    path = tmp_path / "m0.log"
    old = os.umask(0o022)
    try:
        write_log(path, ["install -m0 sysfile"])
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
        path.chmod(0o644)  # a log written by an older version
        append_log(path, "install -m0 sysfile")
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
        fresh = tmp_path / "m1.log"
        append_log(fresh, "install -m1 sysfile")
        assert stat.S_IMODE(fresh.stat().st_mode) == 0o600
    finally:
        os.umask(old)
    assert read_log(path) == ["install -m0 sysfile"] * 2
