"""chcos.serving.loopthread: the one loop-in-a-thread scaffolding of the north servers and the
viewer."""

from __future__ import annotations

import asyncio
import logging
import threading

import pytest

from chcos.serving.loopthread import LoopThread, LoopThreadError

WAIT = 10.0


def test_start_returns_once_ready_and_stop_ends_the_service() -> None:
    seen: list[str] = []
    lt = LoopThread("t-ready")

    async def serve(service: LoopThread) -> None:
        seen.append(threading.current_thread().name)
        service.ready()
        await service.stopped()
        seen.append("cleaned up")

    lt.start(serve)
    assert lt.running and seen == ["t-ready"]
    hit = threading.Event()
    assert lt.call(hit.set)
    assert hit.wait(WAIT)
    lt.stop()
    assert not lt.running and lt.stopping and seen == ["t-ready", "cleaned up"]
    assert lt.loop is not None and lt.loop.is_closed()
    assert not lt.call(hit.set)     # the loop is closed: nothing is scheduled
    lt.stop()                        # idempotent


def test_a_set_up_failure_is_raised_by_start() -> None:
    lt = LoopThread("t-fail")

    async def serve(service: LoopThread) -> None:
        raise OSError("address in use")

    with pytest.raises(OSError, match="address in use"):
        lt.start(serve)
    assert not lt.running


def test_a_service_that_ends_before_ready_is_an_error() -> None:
    async def serve(service: LoopThread) -> None:
        await asyncio.sleep(0)

    with pytest.raises(LoopThreadError, match="ended before it was ready"):
        LoopThread("t-early").start(serve)


def test_a_failure_after_ready_is_logged_and_start_twice_refused(
        caplog: pytest.LogCaptureFixture) -> None:
    lt = LoopThread("t-late")

    async def serve(service: LoopThread) -> None:
        service.ready()
        await service.stopped()
        raise RuntimeError("broke while cleaning up")

    with caplog.at_level(logging.ERROR, logger="chcos.serving.loopthread"):
        lt.start(serve)
        with pytest.raises(LoopThreadError, match="already started"):
            lt.start(serve)
        lt.stop()
    assert any("t-late failed" in r.getMessage() for r in caplog.records)
