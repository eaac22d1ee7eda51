"""Standing tasks and ownership across satellites (issue 16): a standing task's options travel in
the replicated install log, so a satellite that restarts alone runs it again without an invoke;
tasks owned from a satellite that dies are released."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from chcos.satellites.control import LogRequest
from vcan_tests.support_sat import Cluster, device, task

S = "vcan_tests.support_sat"
pytestmark = pytest.mark.slow


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    c = Cluster(tmp_path, machines=(0, 1))
    yield c
    c.close()


def test_restarted_satellite_runs_its_standing_task_again(cluster: Cluster) -> None:
    for m in (0, 1):
        cluster.start(m)
    h = cluster.host
    h.wait_for([0, 1])
    for line in ("install -m0 sysfile", "install -m1 sysfile",
                 f"install -m0i1o1 --standing --restart=on-recovery --backoff=0.2 "
                 f"--code={S}:relay R0 S0 M0"):
        h.execute(line)
    h.execute("inject S0 3")
    doc = cluster.wait_until(lambda d: device(d, "M0")["value"] == 3, machine=0)
    assert task(doc, "R0")["standing"] is True and task(doc, "R0")["restart"] == "on-recovery"
    log = h._ask(1, LogRequest())["log"]
    assert any("--standing" in ln and "--restart=on-recovery" in ln for ln in log), log
    cluster.kill(0)
    cluster.start(0)
    h.wait_for([0, 1])
    cluster.wait_until(lambda d: [t["name"] for t in d["tasks"]] == ["R0"], machine=0)
    h.execute("inject S0 7")  # no invoke: the reloaded satellite started R0 by itself
    cluster.wait_until(lambda d: device(d, "M0")["value"] == 7, machine=0)


def test_tasks_owned_from_a_dead_satellite_are_released(cluster: Cluster) -> None:
    for m in (0, 1):
        cluster.start(m)
    h = cluster.host
    h.wait_for([0, 1])
    for line in ("install -m0 sysfile", "install -m1 sysfile",
                 f"install -m0 --code={S}:worker W", f"install -m1o1 --code={S}:boss LOW W"):
        h.execute(line)
    h.execute("invoke LOW work=60")
    cluster.wait_until(lambda d: task(d, "W")["owner"] == "LOW")
    cluster.kill(1)
    # released (tclose semantics): no owner, suspended (the map may show the release a moment
    # before the suspension under load, so wait for both)
    doc = cluster.wait_until(lambda d: task(d, "W")["owner"] is None
                             and task(d, "W")["status"] == "suspended", machine=0)
    assert task(doc, "W")["status"] == "suspended"
