"""A frame's time budget: the search is anytime, so every stage asks here whether to go on.

``Deadline(ms)`` starts counting when made (or at ``start``, a ``clock()`` reading: the service counts
from before it decodes the image). Stages check it between units of work (level-A anchor chunks,
level-B peaks, polishes, candidate checks) and stop early, recording that they did in ``hit`` (and the
stage they were in, ``stopped_in``); the pipeline then reports the best verified result so far
(``verdict.reason`` "deadline" when that is nothing). ``Deadline(None)`` never expires and costs one
comparison per check.

A deadline bounds the search; it never refuses the first check: until one candidate has been checked
(``checked``), every loop of the search takes its first unit and ``allows_first`` says yes, so a busy
machine's answer is a checked proposal, late, rather than "deadline" with nothing looked at. The running
time estimates (``RunningMean``) then only decide how much more is done, so a slow sample cannot lock
the service into refusing.

``clock`` is injectable so tests can drive a deadline without wall-clock timing.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager


class Deadline:
    def __init__(self, ms: float | None, *, start: float | None = None,
                 clock: Callable[[], float] = time.perf_counter):
        self.clock = clock
        self.ms = None if ms is None else float(ms)
        self.start = clock() if start is None else float(start)
        self.hit = False  # a stage stopped early because of this deadline
        self.stage = "edges"  # what the frame is doing now (the pipeline moves it on)
        self.stopped_in: str | None = None  # the stage in which the deadline was first hit
        self.checks = 0  # candidates checked so far
        self._lap: float | None = None

    def enter(self, stage: str) -> None:
        """The frame moves on to ``stage`` (what ``stopped_in`` names if the deadline is hit there)."""
        self.stage = stage

    def mark_hit(self) -> None:
        if not self.hit:
            self.hit, self.stopped_in = True, self.stage

    def checked(self) -> None:
        """Count a candidate check (refine + evidence + verdict) made under this deadline."""
        self.checks += 1

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
        self.mark_hit()
        return False

    def allows_first(self, cost_ms: float = 0.0) -> bool:
        """``allows``, but always yes until a candidate has been checked: the search and the first check
        are never refused."""
        return self.checks == 0 or self.allows(cost_ms)

    def allows_next(self, reserve_ms: float = 0.0) -> bool:
        """``allows`` for one more unit of a loop of similar units (chunks, scans): the next is taken to
        cost what the one since the previous call did, on top of ``reserve_ms`` kept for later work. Until
        a candidate has been checked, a loop's first unit is always allowed: it is what gives the search
        a proposal to check."""
        if self.ms is None:
            return True
        now = self.clock()
        first = self._lap is None
        unit_ms = 0.0 if first else (now - self._lap) * 1000.0
        self._lap = now
        if first and self.checks == 0:
            return True
        return self.allows(reserve_ms + unit_ms)

    def new_loop(self) -> None:
        """Forget the last unit's duration (``allows_next``): a loop of other units starts."""
        self._lap = None


_PAUSED = 0  # nesting depth of ``timing_paused`` blocks
_PAUSED_LOCK = threading.Lock()


@contextmanager
def timing_paused() -> Iterator[None]:
    """No ``RunningMean`` learns inside: the warm-up's durations are kernel compiles, not a frame's."""
    global _PAUSED
    with _PAUSED_LOCK:
        _PAUSED += 1
    try:
        yield
    finally:
        with _PAUSED_LOCK:
            _PAUSED -= 1


class RunningMean:
    """A running mean of recent durations, ms (exponential, weight ``alpha`` on the newest), and of their
    absolute deviation from it (``spread``; starts at a quarter of the initial mean).

    A sample counts for at most ``MAX_SAMPLE_RATIO`` times the mean (and the initial value): one kernel
    compile or a stalled machine (a 60 s sample) moves the mean a step, not by orders of magnitude, and
    the next ordinary samples bring it back."""

    HIGH_SPREADS = 2.0  # ``high``: about the 90th-95th percentile of durations spread like a normal's
    MAX_SAMPLE_RATIO = 4.0

    def __init__(self, initial_ms: float, alpha: float = 0.2):
        self.initial, self.value, self.alpha = initial_ms, initial_ms, alpha
        self.spread = 0.25 * initial_ms

    def add(self, ms: float) -> None:
        if _PAUSED:
            return
        ms = min(float(ms), self.MAX_SAMPLE_RATIO * max(self.value, self.initial))
        self.spread += self.alpha * (abs(ms - self.value) - self.spread)
        self.value += self.alpha * (ms - self.value)

    @property
    def high(self) -> float:
        """A duration few recent ones exceeded: the mean plus ``HIGH_SPREADS`` mean deviations."""
        return self.value + self.HIGH_SPREADS * self.spread


class _Unbounded(Deadline):
    """The default of functions called without a deadline: it never expires, and as one object shared by
    every frame and thread it keeps no frame's stage or checks."""

    def __init__(self) -> None:
        super().__init__(None)

    def enter(self, stage: str) -> None:
        pass

    def checked(self) -> None:
        pass


NO_DEADLINE = _Unbounded()
