"""Background work: template builds (``build.py``: the build process itself; ``local.py``: this service
process's pool of them; ``queue.py``: jobs on the shared Redis queue that ``python -m service worker``
processes take) and the taught parts' calibrations (``calibrations.py``)."""

from __future__ import annotations

from typing import Any

from service.jobs.local import Builder
from service.settings import Settings


def make_builder(settings: Settings) -> Any:
    """The builds of this service process: its own build processes (``Builder``) with the diskcache,
    or jobs on the shared queue that ``python -m service worker`` processes take (``service.jobs``)
    with Redis."""
    if settings.shared_store:
        from service.jobs.queue import QueueBuilder

        return QueueBuilder(settings)
    return Builder(settings)
