"""What this process's checks take: the anytime estimate's time model (process state, not policy).

Read as ``timing.CHECK_MS`` at each use, so a test can put another model in its place.
"""

from __future__ import annotations

import time

from service.vision.deadline import RunningMean

# Checking a candidate (refine + evidence + verdict): a check starts only when the deadline leaves its
# ``high`` estimate (started on the mean, one in ten answered ~15 ms late), and the anytime search keeps
# that much of its deadline for the first. Starts at a paper render's (1280 x 960) on 2 cores.
CHECK_MS = RunningMean(35.0)
EVIDENCE_MS = 10.0  # judging a refined pose again (its evidence only) on a 1280 x 960 frame


def ms_since(t0: float) -> float:
    """Milliseconds since the ``time.perf_counter()`` reading ``t0``."""
    return (time.perf_counter() - t0) * 1000.0
