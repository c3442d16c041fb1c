"""touchreal_client.events.wait_set: a loop that waits on an often-set event stops at its first
cancellation, whenever that cancellation lands around the set (asyncio.wait_for on 3.10/3.11 loses
some of them: the publisher and the gateway then never stopped)."""

from __future__ import annotations

import asyncio

import pytest
from touchreal_client.events import wait_set
from waiting import until


@pytest.mark.parametrize("yields", [0, 1, 2, 3])
def test_a_waiting_loop_stops_at_the_first_cancel_whenever_the_event_is_set(yields):
    async def go():
        ev, woken = asyncio.Event(), []

        async def loop():
            while True:
                woken.append(await wait_set(ev, 5.0))
                ev.clear()

        task = asyncio.create_task(loop())
        # the loop is inside wait_set, its waiter on the event (asyncio.Event keeps its waiters in _waiters)
        await until(lambda: ev._waiters, 5, "the loop to wait on the event")
        ev.set()
        for _ in range(yields):  # let the set travel part of the way through the waiter
            await asyncio.sleep(0)
        task.cancel()
        done, _ = await asyncio.wait({task}, timeout=1.0)
        return done, task, woken

    done, task, woken = asyncio.run(go())
    assert done and task.cancelled(), "the cancellation was lost: the loop went on"
    assert all(woken)


def test_wait_set_says_whether_the_event_was_set_or_the_time_ran_out():
    async def go():
        ev = asyncio.Event()
        late = await wait_set(ev, 0.02)
        asyncio.get_running_loop().call_later(0.01, ev.set)
        return late, await wait_set(ev, 5.0)

    assert asyncio.run(go()) == (False, True)
