"""One ordered install log under concurrent hosts (issue 19): two hosts installing at the same
moment, round after round, on three satellite processes, never split the log. Every install is
answered with success (a host that lost the race to the other prepared again at the new log
length), every satellite ends with the same log (same length and hash), and every task is in
every satellite's tables at the same link ids. ``CHCOS_RACE_ROUNDS`` sets the number of rounds
(default 50; about 15 s here)."""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from chcos.satellites.control import ChangeRequest, Phase
from chcos.satellites.host import Host, RaceLost
from vcan_tests.support_sat import Cluster

S = "vcan_tests.support_sat"
ROUNDS = int(os.environ.get("CHCOS_RACE_ROUNDS", "50"))
pytestmark = pytest.mark.slow


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    c = Cluster(tmp_path, machines=(0, 1, 2))
    for m in (0, 1, 2):
        c.start(m)
    c.host.wait_for([0, 1, 2])
    for m in (0, 1, 2):
        c.host.execute(f"install -m{m} sysfile")
    yield c
    c.close()


def test_two_hosts_installing_at_once_never_split_the_log(cluster: Cluster) -> None:
    hosts = [Host(cluster.sf, timeout=15.0) for _ in range(2)]
    for h in hosts:
        h.wait_for([0, 1, 2])
    barrier = threading.Barrier(2)
    answers: dict[str, str] = {}
    errors: list[BaseException] = []

    def run(i: int) -> None:
        try:
            for r in range(ROUNDS):
                name = f"H{i}T{r}"
                barrier.wait(timeout=60)
                answers[name] = hosts[i].execute(
                    f"install -m{i}i1 --code={S}:relay {name} S{i}")
        except BaseException as exc:  # reported below
            errors.append(exc)
            barrier.abort()

    threads = [threading.Thread(target=run, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=600)
    assert not errors, errors
    assert len(answers) == 2 * ROUNDS
    heads = cluster.host.log_heads()
    assert len(set(heads.values())) == 1, heads
    assert heads[0][0] == 3 + 2 * ROUNDS
    tables = []
    for m in (0, 1, 2):
        doc = cluster.host.map_doc(m)
        tables.append([(lk["src"], lk["dst"]) for lk in doc["links"]])
        assert sorted(t["name"] for t in doc["tasks"]) == sorted(answers)
    assert tables[0] == tables[1] == tables[2]
    print(f"races lost and retried: {[h.races_lost for h in hosts]}")
    for h in hosts:
        h.close()


def test_a_host_that_lost_the_race_is_told_so(cluster: Cluster) -> None:
    h = cluster.host
    seq = h.log_heads()[0][0]
    h.execute(f"install -m0 --code={S}:worker FIRST")
    # a second host still believing the log has ``seq`` entries
    with pytest.raises(RaceLost, match="another host changed the log"):
        h._ask(0, ChangeRequest(Phase.ACCEPT, f"install -m1 --code={S}:worker LATE", seq, 0))
    with pytest.raises(RaceLost, match="another host changed the log"):
        h._ask(1, ChangeRequest(Phase.PREPARE, f"install -m1 --code={S}:worker LATE", seq))
    with pytest.raises(RaceLost, match="not the sequencer"):
        h._ask(2, ChangeRequest(Phase.ACCEPT, f"install -m1 --code={S}:worker LATE", seq + 1,
                                2))
    assert [t["name"] for t in h.map_doc()["tasks"]] == ["FIRST"]
