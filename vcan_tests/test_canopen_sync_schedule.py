"""The SYNC producer process's schedule (:class:`drivers.canopen_sync.SyncSchedule`, issue 36):
SYNC on absolute deadlines t0 + k * period, a late one followed by the next due one no sooner
than half a period after it (the lost time made up without a burst), and the schedule started
again after a stall longer than MAX_BEHIND. Pure arithmetic on given times (no clock, no bus);
the benchmark (tools/bench_canopen_sync.py) measures the process on SocketCAN. Also: a producer
process that cannot open its socket, and the suite's row for that benchmark where no SocketCAN
guest can run (vcan_tests/test_canopen_sync_socketcan.py has the producer on the wire)."""

from __future__ import annotations

from pathlib import Path

import pytest

from drivers.canopen_sync import MAX_BEHIND, MIN_INTERVAL, SyncSchedule

P = 4_000_000                     # 4 ms in ns
T0 = 10_000_000_000


def test_syncs_on_schedule_go_out_on_the_absolute_grid() -> None:
    s = SyncSchedule(T0, P)
    last = T0
    for k in range(1, 101):
        at = s.next(last + P // 3, last)         # each one asked for a third of a period early
        assert at == T0 + k * P
        last = at + P // 100                     # and sent 1 % of a period late: no drift
    assert s.resynced == 0


def test_a_late_sync_makes_the_next_one_due_on_the_schedule() -> None:
    s = SyncSchedule(T0, P)
    assert s.next(T0, T0) == T0 + P
    late = T0 + P + P // 3                       # SYNC 1 went out a third of a period late
    # the next is due at T0 + 2P on the grid, not one period after the late one
    assert s.next(late, late) == T0 + 2 * P
    assert s.next(T0 + 2 * P, T0 + 2 * P) == T0 + 3 * P


def test_catching_up_never_goes_under_half_a_period() -> None:
    s = SyncSchedule(T0, P)
    s.next(T0, T0)
    last = T0 + P + 3 * P                        # SYNC 1 three periods late (a stall)
    gaps = []
    while (at := s.next(last, last)) != T0 + (2 + len(gaps)) * P:
        gaps.append(at - last)
        last = at
    # the lost time made up at half a period each, then back on the grid
    assert gaps == [round(MIN_INTERVAL * P)] * 5
    assert s.resynced == 0


def test_a_stall_longer_than_max_behind_starts_the_schedule_again() -> None:
    s = SyncSchedule(T0, P)
    s.next(T0, T0)
    stalled = T0 + P + round(MAX_BEHIND * 1e9) + 10 * P   # SYNC 1 went out this late
    assert s.next(stalled, stalled) == stalled        # no catching up a whole second
    assert s.resynced == (stalled - (T0 + 2 * P)) // P
    assert s.next(stalled, stalled) == stalled + P    # on the new grid


def test_a_producer_that_keeps_falling_behind_starts_again_once_a_second_behind() -> None:
    """Woken late for every SYNC (a machine that cannot keep up with the period), the
    producer falls further behind at each one; once MAX_BEHIND behind, it starts again."""
    s = SyncSchedule(T0, P)
    last = T0
    sent = 0
    for _ in range(10_000):                        # a bound: a producer that never starts again
        at = s.next(last, last)
        sent += 1
        if s.resynced:
            break
        last = at + P                              # every SYNC goes out a period late
    assert s.resynced > 0
    # SYNC k is asked for half a period after SYNC k-1 went out, a period late: the producer
    # is k/2 - 1 periods behind at SYNC k, and starts again at the first k past MAX_BEHIND
    assert sent == 2 * (round(MAX_BEHIND * 1e9) // P + 1) + 1
    assert at == last                              # started again from now
    assert s.next(at, at) == at + P                # on the new grid, sent on time


def test_a_period_must_be_positive() -> None:
    with pytest.raises(ValueError, match="SYNC period 0 ns: must be positive"):
        SyncSchedule(T0, 0)


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


def test_a_producer_process_that_cannot_open_its_socket_says_why() -> None:
    """On a host without CAN (no AF_CAN) or an interface that does not exist (in the guest),
    the producer process ends at once and :meth:`start` raises with its words: the driver
    reports them ("cannot start the SYNC producer")."""
    from drivers.canopen_sync import SyncProducerProcess

    errors: list[str] = []
    producer = SyncProducerProcess("chcosnone0", 0.01, errors.append, "test-sync")
    with pytest.raises(OSError, match=r"the SYNC producer process for chcosnone0 did not "
                                      r"start \(exit status 1\): cannot open a raw CAN socket "
                                      r"on chcosnone0: \[Errno \d+\]"):
        producer.start()
    producer.stop()                              # nothing to stop: no error
    assert errors == [] and producer.pid is None
