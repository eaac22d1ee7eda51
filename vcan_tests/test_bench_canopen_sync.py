"""The SYNC benchmark's missed-cycle count (tools/bench_canopen_sync.py :func:`count_cycles`,
issue 36): one definition for the C reference and chcos alike, from the observer's kernel time
stamps: the cycles due in the window from the first SYNC seen, against the SYNCs seen in it.
Pure arithmetic on given time stamps (no clock, no bus); the benchmark itself runs in the
SocketCAN guest."""

from __future__ import annotations

import random

import pytest

from tools.bench_canopen_sync import count_cycles

RATE = 250
P = 4_000_000                     # 4 ms in ns
T0 = 1_700_000_000_000_000_000    # a CLOCK_REALTIME time stamp (ns)
SECONDS = 2.0
N = 500                           # cycles due in SECONDS at RATE
UNTIL = T0 + N * P + 100_000_000  # the observer stopped 0.1 s after the window


def on_schedule(n: int, jitter: int = 0, seed: int = 1) -> list[int]:
    """n SYNC time stamps on the grid T0 + k * P, each off it by up to ``jitter`` ns (the
    first exactly at T0: it opens the window)."""
    rng = random.Random(seed)
    return [T0] + [T0 + k * P + rng.randint(-jitter, jitter) for k in range(1, n)]


def test_a_producer_on_schedule_misses_no_cycle_even_with_jitter() -> None:
    count = count_cycles(on_schedule(N + 200, jitter=P // 3), RATE, SECONDS, UNTIL + 200 * P)
    assert (count.expected, count.seen, count.missed) == (N, N, 0)


def test_all_its_syncs_sent_but_a_backlog_at_the_window_end_counts_as_missed() -> None:
    """The asymmetry this count removes: a producer that sends every one of its N SYNCs, the
    last 7 after the window's end (it fell behind and was still catching up), misses 7 -
    'N sent whenever it finished' no longer counts as 0."""
    stamps = on_schedule(N - 7) + [T0 + N * P + i * P // 2 for i in range(7)]
    assert len(stamps) == N
    assert count_cycles(stamps, RATE, SECONDS, UNTIL + 10 * P).missed == 7


def test_skipped_cycles_are_missed_and_a_burst_inside_the_window_is_not() -> None:
    grid = on_schedule(N + 5)
    skipped = grid[:100] + grid[103:]                    # 3 cycles never sent
    assert count_cycles(skipped, RATE, SECONDS, UNTIL).missed == 3
    # the same 3 sent late, half a period apart, before the window closes: not missed
    caught_up = grid[:100] + [grid[102] + i * P // 2 for i in range(1, 4)] + grid[103:]
    assert count_cycles(caught_up, RATE, SECONDS, UNTIL).missed == 0


def test_a_late_first_sync_opens_the_window_and_the_count_holds() -> None:
    """The window is anchored on the first SYNC seen: a first one 0.4 periods late and the
    rest on the grid still give every cycle its SYNC."""
    stamps = [T0] + [T0 - 4 * P // 10 + k * P for k in range(1, N + 5)]
    assert count_cycles(stamps, RATE, SECONDS, UNTIL).missed == 0


def test_more_syncs_than_due_give_a_negative_count() -> None:
    stamps = sorted([*on_schedule(N + 3), T0 + 10 * P + P // 2, T0 + 20 * P + P // 2])
    count = count_cycles(stamps, RATE, SECONDS, UNTIL)
    assert (count.seen, count.missed) == (N + 2, -2)


def test_no_sync_at_all_misses_every_cycle() -> None:
    assert count_cycles([], RATE, SECONDS, UNTIL).missed == N


def test_an_observer_that_stopped_before_the_window_closed_is_refused() -> None:
    with pytest.raises(ValueError, match=r"the observer stopped 0\.01[0-9] s before the end of "
                                         r"the window of 500 cycles"):
        count_cycles(on_schedule(N - 4), RATE, SECONDS, T0 + (N - 4) * P)


@pytest.mark.parametrize(("rate", "seconds"), [(0, 1.0), (-250, 1.0), (250, 0.0)])
def test_a_rate_or_duration_without_a_cycle_is_refused(rate: int, seconds: float) -> None:
    with pytest.raises(ValueError, match="no cycle to count"):
        count_cycles([T0], rate, seconds, UNTIL)
