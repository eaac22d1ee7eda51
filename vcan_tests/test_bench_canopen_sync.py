"""The SYNC benchmark's missed-cycle count (tools/bench_canopen_sync.py :func:`count_cycles`,
issue 36): one definition for the C reference and chcos alike, from the observer's kernel time
stamps: the cycles due from the producer's first SYNC until it was stopped, against its SYNCs
on the wire in time for them. Pure arithmetic on given time stamps (no clock, no bus); the
benchmark itself runs in the SocketCAN guest."""

from __future__ import annotations

import random

import pytest

from tools.bench_canopen_sync import count_cycles

RATE = 250
P = 4_000_000                     # 4 ms in ns
T0 = 1_700_000_000_000_000_000    # a CLOCK_REALTIME time stamp (ns): the first SYNC
N = 500                           # cycles due by STOP
STOP = T0 + N * P                 # the producer was stopped (2 s after its first SYNC)
UNTIL = STOP + 100_000_000        # the observer stopped 0.1 s later


def on_schedule(n: int, jitter: int = 0, seed: int = 1) -> list[int]:
    """n SYNC time stamps on the grid T0 + k * P, each off it by up to ``jitter`` ns (the
    first exactly at T0: cycle 0)."""
    rng = random.Random(seed)
    return [T0] + [T0 + k * P + rng.randint(-jitter, jitter) for k in range(1, n)]


def test_a_producer_on_schedule_misses_no_cycle_even_with_jitter() -> None:
    """SYNCs up to a third of a period off the grid, and more of them after the stop (the
    producer still running while the observer counts on): every cycle due has its SYNC."""
    count = count_cycles(on_schedule(N + 20, jitter=P // 3), RATE, STOP, UNTIL)
    assert (count.expected, count.seen, count.missed) == (N, N, 0)


def test_all_its_syncs_sent_but_a_backlog_at_the_stop_counts_as_missed() -> None:
    """The asymmetry this count removes: a producer that sends every one of its N SYNCs, the
    last 7 after its stop (it fell behind and was still catching up), misses 7 - 'N sent
    whenever it finished' no longer counts as 0."""
    stamps = on_schedule(N - 7) + [STOP + i * P // 2 for i in range(7)]
    assert len(stamps) == N
    assert count_cycles(stamps, RATE, STOP, UNTIL).missed == 7


def test_skipped_cycles_are_missed_and_a_burst_before_the_stop_is_not() -> None:
    grid = on_schedule(N + 5)
    skipped = grid[:100] + grid[103:]                    # 3 cycles never sent
    assert count_cycles(skipped, RATE, STOP, UNTIL).missed == 3
    # the same 3 sent late, half a period apart, before the stop: not missed
    caught_up = grid[:100] + [grid[102] + i * P // 2 for i in range(1, 4)] + grid[103:]
    assert count_cycles(caught_up, RATE, STOP, UNTIL).missed == 0


def test_the_cycles_due_follow_the_stop_time() -> None:
    """A stop 0.3 periods after a cycle was due still owes that cycle; 0.7 periods after it,
    the next one is due too."""
    stamps = on_schedule(N + 5)
    assert count_cycles(stamps, RATE, STOP + 3 * P // 10, UNTIL).expected == N
    assert count_cycles(stamps, RATE, STOP + 7 * P // 10, UNTIL).expected == N + 1
    assert count_cycles(stamps[:N], RATE, STOP + 7 * P // 10, UNTIL).missed == 1


def test_more_syncs_than_due_give_a_negative_count() -> None:
    """Two SYNCs between cycles (after the first second, which places the grid)."""
    stamps = sorted([*on_schedule(N + 3), T0 + 300 * P + P // 2, T0 + 400 * P + P // 2])
    count = count_cycles(stamps, RATE, STOP, UNTIL)
    assert (count.seen, count.missed) == (N + 2, -2)


def test_an_observer_that_stopped_before_the_cycles_ended_is_refused() -> None:
    with pytest.raises(ValueError, match=r"the observer stopped 0\.01[0-9] s before the end of "
                                         r"the 500 cycles due from the first SYNC"):
        count_cycles(on_schedule(N - 4), RATE, STOP, T0 + (N - 4) * P)


def test_no_sync_a_stop_before_the_first_cycle_or_no_rate_is_refused() -> None:
    with pytest.raises(ValueError, match="the observer saw no SYNC"):
        count_cycles([], RATE, STOP, UNTIL)
    with pytest.raises(ValueError, match="no cycle to count"):
        count_cycles([T0], RATE, T0 + P // 3, UNTIL)
    with pytest.raises(ValueError, match="the rate must be positive"):
        count_cycles([T0], 0, STOP, UNTIL)


def test_a_late_first_sync_does_not_shift_the_grid() -> None:
    """The first SYNC 0.6 periods late (the producer starting), the rest on the grid: cycle 0
    is still due at T0, so the cycles due and the SYNCs seen in time are the same as on
    schedule - neither a cycle credited nor one owed."""
    stamps = [T0 + 6 * P // 10, *on_schedule(N + 5)[1:]]
    count = count_cycles(stamps, RATE, STOP, UNTIL)
    assert (count.expected, count.missed) == (N, 0)
