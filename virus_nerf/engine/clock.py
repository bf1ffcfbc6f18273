"""The frames' clock: a robot's stamps made into one time per stack that only goes forward, across
clock restarts (a bag played again, a clock reset; `Mapper.restart_clock`).

The store keeps each frame at its stamp plus a shift. The shift is 0 until a restart; the first
frame of the new clock (stamped at or before its stack's previous one) sets it so that the new
clock continues RESTART_GAP_S after the newest frame in the store. Frames of a stack still on an
older clock (queued in a driver before the reset) keep that clock's shift.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

RESTART_GAP_S = 1.0  # s between the newest frame and the first after a restart


@dataclass(frozen=True)
class PlacedFrame:
    """Where a frame lands on the store's clock: `time` = `stamp` + `shift` (s)."""

    stack_id: int
    stamp: float  # s, as the robot sent it
    shift: float  # s, the clock's shift
    starts_clock: bool  # the first frame after a restart: it sets the new shift

    @property
    def time(self) -> float:
        return self.stamp + self.shift


class FrameClock:
    """Per stack, its newest frame's (stamp, shift); per clock (its shift), the newest stamp on it.
    `place` changes nothing, `keep` commits a frame that was stored: a refused frame leaves the
    clock as it was."""

    def __init__(self) -> None:
        self.shift = 0.0  # s added to the stamps of the newest clock
        self.restarted = False  # `restart` called: the clock's first frame sets the next shift
        self._stacks: dict[int, tuple[float, float]] = {}  # stack -> its newest frame's (stamp, shift)
        self._newest: dict[float, float] = {}  # a clock's shift -> the newest stamp on it

    def restart(self) -> None:
        self.restarted = True

    def place(self, stack_id: int, stamp: float, store_newest: float | None) -> PlacedFrame:
        """The frame's place on the store's clock; `store_newest`: the newest time in the store
        (s), None when it is empty.

        After `restart` the new clock starts with the first frame stamped at or before its
        stack's previous one (the clock went back); one stamped after it is still the old clock's.
        Later, a frame of a stack whose newest frame is on an older clock takes the clock whose
        newest stamp is nearer its own: a late frame of the old clock keeps the old shift (with the
        new one it would lie a clock's jump ahead and shut its stack's next frames out), a stack's
        first frame of the new clock takes the new one."""
        last = self._stacks.get(stack_id)
        shift, starts = self.shift, False
        if self.restarted:
            if last is None or stamp <= last[0]:  # the clock went back: the new clock starts here
                starts = True
                if store_newest is not None:  # before the first frame there is nothing to follow
                    shift = store_newest + RESTART_GAP_S - stamp
        elif last is not None and last[1] != shift and last[1] in self._newest:
            old, new = self._newest[last[1]], self._newest.get(shift, -math.inf)
            if abs(stamp - old) < abs(stamp - new):
                shift = last[1]  # nearer the old clock's stamps: its frame, arrived late
        return PlacedFrame(stack_id, stamp, shift, starts)

    def keep(self, frame: PlacedFrame) -> None:
        """`frame` is stored: it is its stack's newest, and a restart's first frame sets the shift."""
        self._stacks[frame.stack_id] = (frame.stamp, frame.shift)
        self._newest[frame.shift] = max(self._newest.get(frame.shift, -math.inf), frame.stamp)
        if frame.starts_clock:
            self.shift, self.restarted = frame.shift, False

    def keep_newest(self, stack_id: int, time: float) -> None:
        """A stack's newest frame, stored at `time` (s) on the clock as it is (`Mapper.add_store`)."""
        self.keep(PlacedFrame(stack_id, time - self.shift, self.shift, False))

    def previous_stamp(self, stack_id: int) -> float | None:
        """The stamp of the stack's newest frame, as sent (None before its first)."""
        last = self._stacks.get(stack_id)
        return None if last is None else last[0]

    @property
    def newest_stamp(self) -> float | None:
        """The stamp of the frame newest in the store's time (the newest of each stack's newest
        frames, by stamp plus shift); None before the first frame."""
        if not self._stacks:
            return None
        return max(self._stacks.values(), key=lambda clock: clock[0] + clock[1])[0]
