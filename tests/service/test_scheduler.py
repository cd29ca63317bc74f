"""Absolute-deadline ticks: no drift, missed ticks counted (not sent in a burst), period
changes; timerfd and the asyncio fallback alike. No timing figures are asserted (the
benchmark measures them); only what holds however loaded the machine is."""

from __future__ import annotations

import asyncio
import time

import pytest

from ddh_vsensor.service.scheduler import Sleeper, Ticker, _libc

KINDS = [pytest.param(False, id="asyncio"),
         pytest.param(True, id="timerfd", marks=pytest.mark.skipif(
             _libc() is None, reason="timerfd needs Linux"))]


@pytest.mark.parametrize("use_timerfd", KINDS)
def test_deadlines_are_absolute_and_never_early(use_timerfd: bool) -> None:
    async def scenario():
        ticker = Ticker(0.005, use_timerfd=use_timerfd)
        start = time.monotonic() + 0.005
        ticker.start(first_deadline=start)
        ticks, woke = [], []
        try:
            for _ in range(20):
                tick = await ticker.wait()
                woke.append(time.monotonic())
                ticks.append(tick)
        finally:
            ticker.close()
        return start, ticks, woke, ticker

    start, ticks, woke, ticker = asyncio.run(scenario())
    count = 0
    for tick, t in zip(ticks, woke):
        count += tick.missed + 1
        assert tick.deadline == pytest.approx(start + (count - 1) * 0.005, abs=1e-9)
        assert t >= tick.deadline - 1e-4
    assert ticker.kind == ("timerfd" if use_timerfd else "asyncio")


@pytest.mark.parametrize("use_timerfd", KINDS)
def test_a_blocked_loop_skips_ticks_instead_of_bursting(use_timerfd: bool) -> None:
    async def scenario():
        ticker = Ticker(0.005, use_timerfd=use_timerfd)
        ticker.start()
        try:
            await ticker.wait()
            time.sleep(0.03)                 # the loop is blocked for 6 periods
            late = await ticker.wait()
            nxt = await ticker.wait()
        finally:
            ticker.close()
        return late, nxt

    late, nxt = asyncio.run(scenario())
    assert late.missed >= 4
    # the next deadline follows on the grid (a loaded machine may miss more: counted too)
    assert nxt.deadline == pytest.approx(late.deadline + (nxt.missed + 1) * 0.005, abs=1e-9)


@pytest.mark.parametrize("use_timerfd", KINDS)
def test_period_change_takes_effect_from_the_next_deadline(use_timerfd: bool) -> None:
    async def scenario():
        ticker = Ticker(0.01, use_timerfd=use_timerfd)
        ticker.start()
        try:
            first = await ticker.wait()
            ticker.set_period(0.002)
            ticks = [await ticker.wait() for _ in range(5)]
        finally:
            ticker.close()
        return first, ticks

    first, ticks = asyncio.run(scenario())
    for a, b in zip(ticks, ticks[1:]):          # on the new grid, missed ticks counted
        assert b.deadline - a.deadline == pytest.approx((b.missed + 1) * 0.002, abs=1e-9)
    assert ticks[0].deadline >= first.deadline + 0.002 - 1e-9


@pytest.mark.parametrize("use_timerfd", KINDS)
def test_sleeper_wakes_at_or_after_the_deadline(use_timerfd: bool) -> None:
    async def scenario():
        sleeper = Sleeper(use_timerfd)
        out = []
        try:
            for k in range(5):
                deadline = time.monotonic() + 0.002
                await sleeper.until(deadline)
                out.append(time.monotonic() - deadline)
            await sleeper.until(time.monotonic() - 1.0)     # past: returns at once
        finally:
            sleeper.close()
        return out

    assert all(late >= -1e-4 for late in asyncio.run(scenario()))


@pytest.mark.parametrize("use_timerfd", KINDS)
def test_call_every_ticks_on_the_grid_blocked_loop_and_period_change_included(
        use_timerfd: bool) -> None:
    async def scenario():
        ticker = Ticker(0.005, use_timerfd=use_timerfd)
        start = time.monotonic() + 0.005
        ticker.start(first_deadline=start)
        ticks: list[tuple[object, float]] = []
        blocked = asyncio.Event()

        def on_tick(tick) -> None:
            ticks.append((tick, time.monotonic()))
            if len(ticks) == 5:
                time.sleep(0.03)                 # the loop blocked for 6 periods
            if len(ticks) == 10:
                ticker.set_period(0.002)
            if len(ticks) == 16:
                blocked.set()
        ticker.call_every(on_tick)
        try:
            await asyncio.wait_for(blocked.wait(), 30.0)
        finally:
            ticker.close()
        closed_at = len(ticks)
        await asyncio.sleep(0.02)                # nothing after close
        return start, ticks, closed_at

    start, ticks, closed_at = asyncio.run(scenario())
    assert len(ticks) == closed_at
    count = 0
    for tick, t in ticks[:10]:
        count += tick.missed + 1
        assert tick.deadline == pytest.approx(start + (count - 1) * 0.005, abs=1e-9)
        assert t >= tick.deadline - 1e-4
    assert ticks[5][0].missed >= 4                                    # skipped, no burst
    for (a, _), (b, _) in zip(ticks[11:], ticks[12:]):                # the new period
        assert b.deadline - a.deadline == pytest.approx((b.missed + 1) * 0.002, abs=1e-9)
