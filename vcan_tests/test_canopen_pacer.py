"""The SYNC producer's pacing (:class:`drivers.canopen_sync.SyncPacer`, issue 36): the kernel's
broadcast manager re-arms one period after each expiry, so each late SYNC would push every later
one back; the pacer, told each SYNC's wire time, asks for the next one at its due time on the
absolute schedule, never sooner than half a period after the late one, and starts the schedule
again after a stall longer than MAX_BEHIND. Pure arithmetic on given times (no clock, no bus);
the benchmark (tools/bench_canopen_sync.py) measures it on SocketCAN. Also: the suite's row for
that benchmark where no SocketCAN guest can run."""

from __future__ import annotations

from pathlib import Path

import pytest

from drivers.canopen_sync import MAX_BEHIND, MIN_INTERVAL, SyncPacer

P = 0.004


def test_syncs_on_schedule_ask_for_nothing() -> None:
    pacer = SyncPacer(P)
    assert [pacer.seen(10.0 + k * P + 0.01 * P) for k in range(100)] == [None] * 100
    assert pacer.paced == 0 and pacer.resynced == 0


def test_a_late_sync_makes_the_next_one_due_on_the_schedule() -> None:
    pacer = SyncPacer(P)
    assert pacer.seen(10.0) is None
    # SYNC 1 a third of a period late: the next is due at 10 + 2P, not 10 + P + P/3 + P
    assert pacer.seen(10.0 + P + P / 3) == pytest.approx(10.0 + 2 * P)
    assert pacer.seen(10.0 + 2 * P) is None           # back on schedule
    assert pacer.paced == 1


def test_catching_up_never_asks_for_an_interval_under_half_a_period() -> None:
    pacer = SyncPacer(P)
    pacer.seen(0.0)
    at = 1 * P + 3 * P                                # SYNC 1 three periods late (a stall)
    asked = []
    for _ in range(10):
        nxt = pacer.seen(at)
        if nxt is None:
            break
        assert nxt - at >= MIN_INTERVAL * P - 1e-12
        asked.append(nxt - at)
        at = nxt                                      # the producer sends when asked
    # the lost time made up over the following cycles at half a period each, then on schedule
    assert asked == [pytest.approx(MIN_INTERVAL * P)] * 6
    assert at == pytest.approx(0.0 + (1 + len(asked)) * P)


def test_a_stall_longer_than_max_behind_starts_the_schedule_again() -> None:
    pacer = SyncPacer(P)
    pacer.seen(0.0)
    late = P + MAX_BEHIND + 10 * P
    assert pacer.seen(late) is None                   # no catching up a whole second
    assert pacer.resynced == int((MAX_BEHIND + 10 * P) / P)
    assert pacer.seen(late + P) is None               # on the new schedule
    assert pacer.paced == 0


def test_the_suite_row_says_not_measured_without_a_guest(tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    from tools.suite_common import SuiteRun
    from tools.suite_sections import canopen_sync

    monkeypatch.setenv("CHCOS_UML_KERNEL", str(tmp_path / "no-such-kernel"))
    run = SuiteRun(quick=True, reps=1, seed=0, out=tmp_path, soak_s=1.0, saturated_s=1.0)
    canopen_sync(run)
    assert run.rows == [("CANopen SYNC cycle on SocketCAN beside a C producer", "-",
                         "not measured: no SocketCAN guest (no User-Mode-Linux kernel: "
                         "apt-get install user-mode-linux)", "-")]
    assert run.res["canopen_sync"]["results"] == []
