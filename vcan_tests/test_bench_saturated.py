"""The saturated-bus benchmark runs briefly and its frame accounting adds up (not a timing test)."""

from __future__ import annotations

from chcos.apps.bench.saturated import N_IDS, report, run_saturated


def test_saturated_accounting_adds_up() -> None:
    r = run_saturated(1.0, rate_in=2000.0, rate_out=200.0, warmup=0.2)
    assert r.unaccounted() == {k: 0 for k in r.unaccounted()}, report(r)
    assert r.sent > 0 and r.sent == r.received_by_driver == r.readings + r.dropped + r.bus_errors
    assert r.requests > 0 and r.answers_received == r.answers_sent == r.answers_written
    # queued sensor links: every request reaches its task and is answered
    assert r.consumed == r.readings and r.unanswered == 0, report(r)
    assert r.reaction and 0 < r.percentile(0.99) <= r.percentile(1.0)
    assert r.cpu_process >= r.cpu_peer >= 0 and r.cpus >= 1 and r.queue > 0
    assert "lost without a count: none" in report(r)


def test_newest_wins_counts_what_it_overwrites() -> None:
    r = run_saturated(1.0, rate_in=2000.0, rate_out=200.0, warmup=0.2, queue=0)
    assert r.unaccounted() == {k: 0 for k in r.unaccounted()}, report(r)
    unread = r.readings - r.consumed - r.overwritten
    assert 0 <= unread <= N_IDS
