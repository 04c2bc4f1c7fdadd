"""A frame's time budget: the search is anytime, so every stage asks here whether to go on.

``Deadline(ms)`` starts counting when made (or at ``start``, a ``clock()`` reading: the service counts
from before it decodes the image). Stages check it between units of work (level-A anchor chunks,
level-B peaks, polishes, candidate checks) and stop early, recording that they did in ``hit``; the
pipeline then reports the best verified result so far (``verdict.reason`` "deadline" when that is
nothing). ``Deadline(None)`` never expires and costs one comparison per check.

``clock`` is injectable so tests can drive a deadline without wall-clock timing.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable


class Deadline:
    def __init__(self, ms: float | None, *, start: float | None = None,
                 clock: Callable[[], float] = time.perf_counter):
        self.clock = clock
        self.ms = None if ms is None else float(ms)
        self.start = clock() if start is None else float(start)
        self.hit = False  # a stage stopped early because of this deadline
        self._lap: float | None = None

    def left_ms(self) -> float:
        """Milliseconds until the deadline (inf without one; negative once past)."""
        if self.ms is None:
            return math.inf
        return self.ms - (self.clock() - self.start) * 1000.0

    def allows(self, cost_ms: float = 0.0) -> bool:
        """Whether work expected to take ``cost_ms`` still fits; marks the deadline ``hit`` if not."""
        if self.ms is None:
            return True
        if self.left_ms() >= cost_ms:
            return True
        self.hit = True
        return False


    def allows_next(self, reserve_ms: float = 0.0) -> bool:
        """``allows`` for one more unit of a loop of similar units (chunks, scans): the next is taken to
        cost what the one since the previous call did, on top of ``reserve_ms`` kept for later work."""
        if self.ms is None:
            return True
        now = self.clock()
        unit_ms = 0.0 if self._lap is None else (now - self._lap) * 1000.0
        self._lap = now
        return self.allows(reserve_ms + unit_ms)

    def new_loop(self) -> None:
        """Forget the last unit's duration (``allows_next``): a loop of other units starts."""
        self._lap = None


class RunningMean:
    """A running mean of recent durations, ms (exponential, weight ``alpha`` on the newest), and of their
    absolute deviation from it (``spread``; starts at a quarter of the initial mean)."""

    HIGH_SPREADS = 2.0  # ``high``: about the 90th-95th percentile of durations spread like a normal's

    def __init__(self, initial_ms: float, alpha: float = 0.2):
        self.value, self.alpha = initial_ms, alpha
        self.spread = 0.25 * initial_ms

    def add(self, ms: float) -> None:
        self.spread += self.alpha * (abs(ms - self.value) - self.spread)
        self.value += self.alpha * (ms - self.value)

    @property
    def high(self) -> float:
        """A duration few recent ones exceeded: the mean plus ``HIGH_SPREADS`` mean deviations."""
        return self.value + self.HIGH_SPREADS * self.spread


NO_DEADLINE = Deadline(None)
