"""Install logs that cannot diverge (issue 50): the sequencer, a follower, or both are killed
(SIGKILL, by themselves, at a point named by ``CHCOS_TEST_CRASH_AT``) at every step of the
commit path - before and after prepare, accept and commit - on three satellite processes. Each
time the host's answer is what the replicated log holds (the install succeeds on the
satellites still up), the killed satellites rejoin by themselves (no log moved away, no
operator), and every satellite ends with the same log, holding each install exactly once.
``CHCOS_CRASH_ROUNDS`` repeats the whole loop (default 1: 18 trials)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from chcos.satellites.control import LogRequest, Phase
from vcan_tests.support_sat import Cluster

S = "vcan_tests.support_sat"
ROUNDS = int(os.environ.get("CHCOS_CRASH_ROUNDS", "1"))
POINTS = [f"{phase.value}:{when}" for phase in Phase for when in ("before", "after")]
#: who is killed: the sequencer (machine 0), a follower (machine 1), both
VICTIMS = [(0,), (1,), (0, 1)]
pytestmark = pytest.mark.slow


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    c = Cluster(tmp_path, machines=(0, 1, 2))
    for m in (0, 1, 2):
        c.start(m)
    c.host.timeout = 5.0
    c.host.wait_for([0, 1, 2])
    for m in (0, 1, 2):
        c.host.execute(f"install -m{m} sysfile")
    yield c
    c.close()


def _restart(cluster: Cluster, machines: tuple[int, ...], env: dict[str, str] | None) -> None:
    for m in machines:
        cluster.kill(m)  # reaps a satellite that killed itself; waits for its token to go
    for m in machines:
        cluster.start(m, env)
    cluster.host.wait_for([0, 1, 2], timeout=60)


def test_satellites_killed_at_every_step_of_the_commit_path_rejoin_with_one_log(
        cluster: Cluster) -> None:
    host = cluster.host
    installed: list[str] = []
    trials = 0
    for rnd in range(ROUNDS):
        for victims in VICTIMS:
            for point in POINTS:
                _restart(cluster, victims, {"CHCOS_TEST_CRASH_AT": point})
                name = f"R{rnd}{''.join(map(str, victims))}{point.replace(':', '')}"
                line = f"install -m2i1 --code={S}:relay {name.upper()} S1"
                answer = host.execute(line)
                assert "installed" in answer or "committed" in answer, answer
                installed.append(name.upper())
                for m in victims:  # each killed itself at that point
                    assert cluster.procs[m].wait(30) == -9, (point, m)
                _restart(cluster, victims, None)  # rejoins by itself
                heads = host.log_heads()
                assert sorted(heads) == [0, 1, 2]
                assert len(set(heads.values())) == 1, (point, victims, heads)
                trials += 1
    logs = {m: host._ask(m, LogRequest())["log"] for m in (0, 1, 2)}
    assert logs[0] == logs[1] == logs[2]
    tasks = [line.split()[-2] for line in logs[0] if "--code" in line]
    assert tasks == installed  # each exactly once, in order
    for m in (0, 1, 2):
        names = sorted(t["name"] for t in host.map_doc(m)["tasks"])
        assert names == sorted(installed)
    dropped = sum((cluster.tmp / f"sat{m}.log").read_text().count("uncommitted log entry")
                  for m in (0, 1))
    print(f"kill-loop trials: {trials}, all rejoined with identical logs of {len(logs[0])} "
          f"entries; uncommitted entries settled on restart: {dropped}")
