"""The store: ``open_store(location)`` opens the backend a location names; ``base.py`` holds the ``Store``
interface and what both backends share, ``disk.py`` (diskcache) and ``redis.py`` (Redis) implement it."""

from __future__ import annotations

import os
from typing import Any

from service.stores.base import Store, is_shared


def open_store(location: str | os.PathLike[str], **kwargs: Any) -> Store:
    """The backend ``location`` names: a ``redis://``, ``rediss://`` or ``unix://`` URL, else a cache
    directory. ``kwargs``: the backend's options (``bank_cache_mb``)."""
    if is_shared(location):
        from service.stores.redis import RedisStore

        return RedisStore(location, **kwargs)
    from service.stores.disk import DiskStore

    return DiskStore(location, **kwargs)
