"""A lockstep clock shared by several flight loops in one event loop: a barrier.

Each loop gets its own ``member()`` clock. ``await member.sleep_until(t)`` parks the loop; the
world is stepped only when every member still flying is parked, and then only to the earliest
time asked for, after which the members due are released (in join order). So N loops of one
fleet see exactly the same simulated instants as N lockstep flights would, and none of them
runs ahead of the others. A member that ``leave()``s (its flight ended) no longer holds the
others back.
"""

from __future__ import annotations

import asyncio

from cfknode.kernel.clock import Steppable

_EPS = 1e-12


class FleetClock:
    """The barrier over one ``Steppable`` world."""

    def __init__(self, world: Steppable) -> None:
        self._world = world
        self._members: list[MemberClock] = []
        self._waiting: dict[int, tuple[float, asyncio.Future[None]]] = {}
        self.steps = 0  # how many times the barrier stepped the world

    def member(self) -> "MemberClock":
        clock = MemberClock(self, len(self._members))
        self._members.append(clock)
        return clock

    def now(self) -> float:
        return self._world.t

    async def _wait(self, index: int, t: float) -> None:
        future: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._waiting[index] = (t, future)
        self._release()
        await future

    def _leave(self, index: int) -> None:
        member = self._members[index]
        if member.active:
            member.active = False
            self._release()

    def _release(self) -> None:
        active = [m.index for m in self._members if m.active]
        if not active or any(i not in self._waiting for i in active):
            return
        t_min = min(self._waiting[i][0] for i in active)
        if t_min > self._world.t:
            self._world.step_to(t_min)
            self.steps += 1
        now = self._world.t
        for i in active:
            t, future = self._waiting[i]
            if t <= now + _EPS:
                del self._waiting[i]
                if not future.done():
                    future.set_result(None)


class MemberClock:
    """One flight loop's view of a ``FleetClock`` (the ``Clock`` protocol, lockstep)."""

    lockstep = True

    def __init__(self, fleet: FleetClock, index: int) -> None:
        self._fleet = fleet
        self.index = index
        self.active = True

    def now(self) -> float:
        return self._fleet.now()

    async def sleep_until(self, t: float) -> None:
        if not self.active:
            raise RuntimeError("this flight has left the fleet clock")
        await self._fleet._wait(self.index, t)

    def leave(self) -> None:
        """This loop is done: the others stop waiting for it."""
        self._fleet._leave(self.index)


__all__ = ["FleetClock", "MemberClock"]
