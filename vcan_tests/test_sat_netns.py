"""Satellites on separate hosts (issue 19): three satellites and the host each in a Linux network
namespace of their own, joined by veth pairs to a bridge on a private test subnet (10.19.0.0/24,
made by the test and removed after it, also on failure), talking mutual TLS with certificates
the test makes with openssl. Checks the figure 6.5 script across the hosts, cross-satellite
messages, an e-stop that reaches every satellite, a killed satellite noticed and its return,
and that a process in a fourth namespace without the system's credentials is refused. Needs
root, ``ip`` and ``openssl``; under ``CI=true`` a missing one fails the test."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
from pathlib import Path
from typing import Any

import pytest

from chcos.apps import fig65
from vcan_tests.support_netns import Net, RemoteHost, missing, pki, tls_section
from vcan_tests.support_sat import device, link, task

ROOT = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.slow
NODES = {"s0": 1, "s1": 2, "s2": 3, "h": 10, "r": 66}
REACH = 8.0
"""Seconds a session without the system's credentials is given to reach a satellite (a session
with them reaches every satellite well within it: the test checks so first)."""


def _require() -> None:
    why = missing()
    if why:
        if os.environ.get("CI") == "true":
            pytest.fail(f"the network-namespace tests need {why}")
        pytest.skip(f"needs {why}")


def _system(tmp: Path, name: str, tls: str, secret: Path, addresses: dict[str, str]) -> Path:
    sats = "".join(f'[[satellite]]\nmachine = {m}\nport = 7447\nhost = "{addresses[f"s{m}"]}"\n'
                   for m in (0, 1, 2))
    path = tmp / f"{name}.toml"
    path.write_text(
        f'[system]\nname = "fig65net"\ndevmaps = ["{ROOT}/chcos/apps/fig65/fig65.toml"]\n'
        f'task_path = ["{fig65.HERE}"]\nbase_dir = "{tmp}"\nstate_dir = "{tmp}/state-{name}"\n'
        f'secret_file = "{secret}"\n\n{sats}\n[link]\nlease_ms = 1000\n{tls}')
    return path


def _wait_log(host: RemoteHost, logs: list[Path], text: str) -> None:
    def seen(_doc: Any) -> bool:
        return all(text in p.read_text(errors="replace") for p in logs)
    host.wait_until(seen)


def test_three_hosts_over_mutual_tls(tmp_path: Path) -> None:
    _require()
    shutil.copy(fig65.HERE / "testfile", tmp_path / "testfile")
    net = Net(NODES)
    procs: dict[int, subprocess.Popen[Any]] = {}
    hosts: list[RemoteHost] = []
    try:
        addrs = net.addresses
        good = tls_section(*pki(tmp_path / "pki", [addrs[n] for n in ("s0", "s1", "s2", "h")]))
        system = _system(tmp_path, "system", good, tmp_path / "secret.json", addrs)
        logs = [tmp_path / f"sat{m}.log" for m in (0, 1, 2)]

        def start(m: int) -> None:
            procs[m] = net.popen(f"s{m}", ["-m", "chcos.cli.main", "-v", "satellite", "-m", str(m),
                                           "--system", str(system)], logs[m])

        for m in (0, 1, 2):
            start(m)
        host = RemoteHost(net, "h", system, tmp_path / "host.log")
        hosts.append(host)
        host.call("wait_for", machines=[0, 1, 2], timeout=60)
        for line in fig65.SCRIPT.read_text().splitlines():
            host.call("exec", line=line)
        host.call("exec", line="install -m2 --code=vcan_tests.support_netns:stopper STOP")
        host.call("exec", line="invoke C1")
        doc = host.wait_until(lambda d: task(d, "B1")["owner"] == "C1"
                              and link(d, "A2", "B1")["delivered"] > 0    # machine 1 -> 0
                              and link(d, "A3", "B2")["delivered"] > 0)   # machine 2 -> 1
        assert [(t["name"], t["machine"]) for t in doc["tasks"]] == [
            ("A1", 0), ("A2", 1), ("A3", 2), ("A4", 2), ("B1", 0), ("B2", 1), ("C1", 2),
            ("STOP", 2)]
        heads = host.call("heads")
        assert len({tuple(v) for v in heads.values()}) == 1 and len(heads) == 3

        # an e-stop on machine 2 reaches every satellite
        host.call("exec", line="invoke STOP why=netns-stop")
        _wait_log(host, logs, "estop (netns-stop)")

        # a killed satellite is noticed by the others, and comes back with the same tables
        procs.pop(1).send_signal(signal.SIGKILL)
        doc = host.wait_until(lambda d: device(d, "S3")["status"] == "failed", machine=0)
        assert device(doc, "S1")["status"] == "OK"
        start(1)
        host.call("wait_for", machines=[0, 1, 2], timeout=60)
        doc = host.wait_until(lambda d: device(d, "S3")["status"] == "OK", machine=0)
        assert [t["name"] for t in host.call("map", machine=1)["tasks"]] == [
            t["name"] for t in doc["tasks"]]
        assert len({tuple(v) for v in host.call("heads").values()}) == 1

        # the refusals below are given REACH seconds to reach a satellite: a fresh session
        # holding the system's credentials does within that (control)
        fresh = RemoteHost(net, "h", system, tmp_path / "fresh.log", reach=REACH)
        hosts.append(fresh)
        assert len(fresh.call("heads")) == 3

        # a process in a fourth namespace without the system's credentials: another CA and
        # another secret. It reaches no satellite, and changes nothing.
        bad = tls_section(*pki(tmp_path / "rogue-pki", [addrs["r"]], cn="rogue CA"))
        rogue_sys = _system(tmp_path, "rogue", bad, tmp_path / "rogue-secret.json", addrs)
        rogue = RemoteHost(net, "r", rogue_sys, tmp_path / "rogue.log", reach=REACH)
        hosts.append(rogue)
        with pytest.raises(RuntimeError, match="no satellite of fig65net is reachable"):
            rogue.call("exec", line="install -m0 --code=vcan_tests.support_netns:stopper EVIL")
        assert "EVIL" not in [t["name"] for t in host.call("map")["tasks"]]
        # the same process holding the system's certificates but not its secret
        rogue2_sys = _system(tmp_path, "rogue2", good, tmp_path / "rogue-secret.json", addrs)
        rogue2 = RemoteHost(net, "r", rogue2_sys, tmp_path / "rogue2.log", reach=REACH)
        hosts.append(rogue2)
        with pytest.raises(RuntimeError, match="no satellite of fig65net is reachable"):
            rogue2.call("exec", line="invoke STOP why=rogue")
    finally:
        for h in hosts:
            h.close()
        for p in procs.values():
            p.terminate()
        for p in procs.values():
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                p.kill()
        net.close()
    assert not [ns for ns in subprocess.run(["ip", "netns", "list"], capture_output=True,
                                            text=True).stdout.split() if ns.startswith(net.tag)]
