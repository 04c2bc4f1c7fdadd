"""The store backends behind ``service.store.Store``: disk.py (diskcache), redis.py (Redis)."""
