"""Satellites as separate processes on loopback, over Zenoh: the thesis' three-machine install
script, cross-satellite pre-emption, a late joiner, a killed satellite, an unauthenticated host."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest

from chcos.apps import fig65
from chcos.errors import InstallError, LinkError
from chcos.satellites.host import Host
from vcan_tests.support_sat import Cluster, device, link, task

S = "vcan_tests.support_sat"
pytestmark = pytest.mark.slow


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    c = Cluster(tmp_path)
    yield c
    c.close()


def test_figure_6_5_on_three_satellites(tmp_path: Path) -> None:
    shutil.copy(fig65.HERE / "testfile", tmp_path / "testfile")
    root = Path(__file__).resolve().parent.parent
    c = Cluster(tmp_path)
    (tmp_path / "system.toml").write_text(
        (tmp_path / "system.toml").read_text().replace(
            'devmaps = ["devices.toml"]',
            f'devmaps = ["{root}/chcos/apps/fig65/fig65.toml"]\ntask_path = ["{fig65.HERE}"]'))
    from chcos.satellites import sysfile

    c.sf = sysfile.load(tmp_path / "system.toml")
    try:
        for m in (0, 1, 2):
            c.start(m)
        c.host.wait_for([0, 1, 2])
        for line in fig65.SCRIPT.read_text().splitlines():
            c.host.execute(line)
        c.host.execute("invoke C1")
        doc = c.wait_until(lambda d: task(d, "B1")["owner"] == "C1"
                           and task(d, "A2")["steps"] > 5 and task(d, "B2")["steps"] > 5
                           and link(d, "A2", "B1")["delivered"] > 0)
        assert [(t["name"], t["machine"]) for t in doc["tasks"]] == [
            ("A1", 0), ("A2", 1), ("A3", 2), ("A4", 2), ("B1", 0), ("B2", 1), ("C1", 2)]
        assert link(doc, "C1", "B1")["priority"] == 9
        # every satellite keeps the same message table
        views = [c.host.map_doc(m) for m in (0, 1, 2)]
        assert len({tuple((lk["src"], lk["dst"], lk["priority"]) for lk in v["links"])
                    for v in views}) == 1
        c.host.execute("inject /dev/tty0 stop")
        c.wait_until(lambda d: link(d, "host", "C1")["status"] == "normal completion"
                     or task(d, "C1")["completions"] == 1)
    finally:
        c.close()


def test_cross_satellite_preemption(cluster: Cluster) -> None:
    for m in (0, 1, 2):
        cluster.start(m)
    h = cluster.host
    h.wait_for([0, 1, 2])
    for line in ("install -m0 sysfile", "install -m1 sysfile", "install -m2 sysfile",
                 f"install -m0 --code={S}:worker W",
                 f"install -m1o1 --code={S}:boss LOW W",
                 f"install -m2o1 --code={S}:boss HIGH W",
                 "setpri -2 LOW W", "setpri -20 HIGH W"):
        h.execute(line)
    h.execute("invoke LOW work=30")
    # LOW owns W and has had W's model's answer (the ask crosses two satellites) before HIGH
    # takes W: else the answer may already name HIGH
    cluster.wait_until(lambda d: task(d, "W")["owner"] == "LOW" and
                       task(d, "LOW")["world"]["command"].get("W serves") == "LOW")
    h.execute("invoke HIGH work=0.5")
    doc = cluster.wait_until(lambda d: link(d, "HIGH", "W")["status"] == "normal completion"
                             and task(d, "W")["owner"] is None)
    assert link(doc, "LOW", "W")["status"] == "pre-empted"
    assert task(doc, "W")["completions"] == 1
    # each owner asked W's world model (on machine 0) whom it serves, over the link
    assert task(doc, "LOW")["world"]["command"]["W serves"] == "LOW"
    assert task(doc, "HIGH")["world"]["command"]["W serves"] == "HIGH"


def test_late_joiner_catches_up_before_it_runs(cluster: Cluster) -> None:
    cluster.start(0)
    cluster.start(1)
    h = cluster.host
    h.wait_for([0, 1])
    for line in ("install -m0 sysfile", "install -m1 sysfile", "install -m2 sysfile",
                 f"install -m0i1o1 --code={S}:relay R0 S0 M0",
                 f"install -m2i1 --code={S}:relay R2 R0",
                 "setpri -30 R0 R2"):
        h.execute(line)
    cluster.start(2)
    h.wait_for([0, 1, 2])
    doc = h.map_doc(2)
    assert [t["name"] for t in doc["tasks"]] == ["R0", "R2"]
    assert link(doc, "R0", "R2")["priority"] == 30
    h.execute("invoke R0")
    h.execute("invoke R2")
    h.execute("inject S0 7")
    doc = cluster.wait_until(lambda d: link(d, "R0", "R2")["delivered"] == 1)
    assert device(doc, "M0")["value"] == 7


def test_killed_satellite_is_noticed_and_reloaded(cluster: Cluster) -> None:
    for m in (0, 1):
        cluster.start(m)
    h = cluster.host
    h.wait_for([0, 1])
    for line in ("install -m0 sysfile", "install -m1 sysfile",
                 f"install -m0 --code={S}:worker W", f"install -m1o1 --code={S}:boss LOW W"):
        h.execute(line)
    h.execute("invoke LOW work=60")
    cluster.wait_until(lambda d: task(d, "W")["owner"] == "LOW")
    cluster.kill(0)
    doc = cluster.wait_until(lambda d: link(d, "LOW", "W")["status"] == "abnormal completion",
                             machine=1)
    assert device(doc, "S0")["status"] == "failed" and device(doc, "M0")["status"] == "failed"
    assert device(doc, "S1")["status"] == "OK"  # the rest continues
    cluster.start(0)
    h.wait_for([0, 1])
    doc = cluster.wait_until(lambda d: [t["name"] for t in d["tasks"]] == ["W", "LOW"]
                             and device(d, "S0")["status"] == "OK", machine=0)
    assert task(doc, "W")["machine"] == 0


def test_unauthenticated_host_is_refused_and_tables_unchanged(tmp_path: Path) -> None:
    c = Cluster(tmp_path, machines=(0, 1), auth=True)
    try:
        c.start(0)
        c.start(1)
        good = Host(c.sf, auth=("host", "s3cret"), timeout=15.0)
        good.wait_for([0, 1])
        good.execute("install -m0 sysfile")
        with Host(c.sf, auth=("intruder", "guess"), timeout=3.0, settle=0.5) as bad, \
                pytest.raises(LinkError, match="not authenticated"):
            bad.execute(f"install -m0 --code={S}:worker X")
        with Host(c.sf, auth=("", ""), timeout=3.0, settle=0.5) as anonymous, \
                pytest.raises(LinkError):
            anonymous.execute(f"install -m0 --code={S}:worker X")
        with pytest.raises(InstallError, match=r"no module no\.such"):
            good.execute("install -m0 --code=no.such:task Y")  # malformed: refused, logged
        assert good.map_doc()["tasks"] == []
        good.close()
        assert "no module no.such" in (tmp_path / "sat0.log").read_text()
    finally:
        c.close()
