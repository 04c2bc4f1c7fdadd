"""Template builds as jobs on a Redis queue (with ``POSE_STORE=redis://...``).

Why RQ: the store is already Redis, and RQ needs nothing else (no broker, no result backend, no
scheduler process); its API is synchronous like the build; and each job runs in a forked work-horse
that ends with the job, so a build's memory is freed when it ends (what the per-build process gives
the single-machine ``Builder``). Celery would add a broker abstraction and a config surface this
service does not need; arq and dramatiq are asyncio- or broker-first.

API replicas enqueue (``QueueBuilder``); ``python -m service worker`` processes, any number on any
machine, take the jobs (``worker_main``)::

    upload on any replica -> enqueue build(mid) -> a worker's horse: run_build(REDIS_URL, mid)

``run_build`` takes the model's lease (``posecell:v1:lock:<id>``, SET NX PX, renewed every
lease/3) before building, so a build never runs twice at once even when its job was enqueued twice;
progress goes to the record every replica reads. A worker killed mid-build (kill -9, a lost
machine) stops renewing; once its lease has expired, the sweep (``sweep``, every lease/3 in every
live worker) sees an unfinished model with no lease holder and no queued job for a whole lease
period, and enqueues it again: another worker builds it. A job is one build attempt; the sweep is
the retry (so a build whose worker keeps dying is retried without bound; see the README).
"""

from __future__ import annotations

import logging
import os
import threading
import time
import uuid
from typing import Any

import redis
from rq import Queue, Worker

from service.jobs.build import limit_memory, run_build
from service.settings import Settings
from service.stores import open_store
from service.stores.base import Store

log = logging.getLogger("service")

QUEUE_NAME = "posecell:v1:builds"
JOB_PREFIX = "build-"
JOB_TIMEOUT_S = 6 * 3600  # RQ kills a horse after this; a build is bounded well below it
RESULT_TTL_S = 3600


def build_job(location: str, mid: str, lease_s: float, memory_mb: int, threads: int | None) -> str:
    """One build attempt, in an RQ work-horse: capped memory, the service's thread budget."""
    from service.vision import threads as thread_budget

    thread_budget.configure(threads)
    limit_memory(memory_mb)
    # the horse ends with its worker: killed mid-build, the worker leaves no orphan build behind (the
    # model goes back to "queued", its lease is released and another worker's sweep re-queues it)
    status = run_build(location, mid, lease_s, parent_pid=os.getppid(), memory_mb=memory_mb)
    log.info("template build of model %s: %s", mid, status)
    return status


def _connection(settings: Settings) -> redis.Redis:
    return redis.Redis.from_url(settings.store_location, socket_timeout=30, socket_connect_timeout=5)


def queued_ids(queue: Queue) -> set[str]:
    """Model ids that have a build job waiting in ``queue``."""
    return {j[len(JOB_PREFIX):].rsplit("-", 1)[0] for j in queue.get_job_ids() if j.startswith(JOB_PREFIX)}


def enqueue(queue: Queue, settings: Settings, mid: str) -> None:
    queue.enqueue_call(build_job, args=(settings.store_location, mid, float(settings.build_lease_s),
                                        int(settings.build_memory_mb), settings.threads),
                       job_id=f"{JOB_PREFIX}{mid}-{uuid.uuid4().hex[:8]}", timeout=JOB_TIMEOUT_S,
                       result_ttl=RESULT_TTL_S, failure_ttl=RESULT_TTL_S, description=f"build {mid}")


def sweep(store: Store, queue: Queue, settings: Settings, orphans: dict[str, float] | None = None,
          *, grace_s: float = 0.0) -> list[str]:
    """Enqueue every unfinished model that nobody builds (no lease) and nobody waits for (no job).

    With ``orphans`` (model id -> when it was first seen so, kept between calls), only a model seen
    so for ``grace_s``: a job just taken by a worker holds no lease while its horse starts up (a
    duplicate would be harmless, the lease lets one build, but it would keep a worker waiting)."""
    waiting = queued_ids(queue)
    now = time.monotonic()
    seen = [mid for mid in store.unfinished() if mid not in waiting and store.lock_holder(mid) is None]
    if orphans is None:
        again = seen
    else:
        for mid in list(orphans):
            if mid not in seen:
                del orphans[mid]
        again = [mid for mid in seen if now - orphans.setdefault(mid, now) >= grace_s]
        for mid in again:
            del orphans[mid]
    for mid in again:
        log.info("re-queueing the template build of model %s (no worker holds it)", mid)
        enqueue(queue, settings, mid)
    return again


class QueueBuilder:
    """The ``Builder`` of an API replica with the shared store: builds go to the queue, not here."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.queue = Queue(QUEUE_NAME, connection=_connection(settings))

    def submit(self, mid: str) -> None:
        if mid not in queued_ids(self.queue):
            enqueue(self.queue, self.settings, mid)

    def resume(self, store: Store) -> list[str]:
        try:
            return sweep(store, self.queue, self.settings)
        except redis.RedisError as e:  # the replica starts without Redis; /health says so, workers sweep
            log.error("could not re-queue unfinished builds: %s", e)
            return []

    def running(self) -> dict[str, int]:
        return {}  # builds run in workers, not in this process

    def cancel(self, mid: str) -> bool:
        """Drop queued jobs of ``mid``; a running build sees its model gone and stops (``run_build``)."""
        for job_id in self.queue.get_job_ids():
            if job_id.startswith(f"{JOB_PREFIX}{mid}-"):
                self.queue.remove(job_id)
        return False

    def shutdown(self) -> None:
        self.queue.connection.close()


def worker_main(settings: Settings, *, burst: bool = False) -> int:
    """``python -m service worker``: take build jobs until stopped. SIGTERM: RQ's warm shutdown lets
    the running build finish, then exits; a second SIGTERM kills the build's horse, and the build is
    taken over by another worker once its lease has run out (``POSE_BUILD_LEASE_S``)."""
    if not settings.shared_store:
        raise SystemExit("python -m service worker needs POSE_STORE=redis://host:6379/0 (the shared store); "
                         "with the default diskcache, `python -m service serve` builds in its own processes")
    conn = _connection(settings)
    queue = Queue(QUEUE_NAME, connection=conn)
    stop = threading.Event()
    period_s = max(0.5, float(settings.build_lease_s) / 3)

    def sweeper() -> None:
        orphans: dict[str, float] = {}
        with open_store(settings.store_location) as store:
            while not stop.wait(period_s):
                try:
                    sweep(store, queue, settings, orphans, grace_s=float(settings.build_lease_s))
                except Exception as e:  # Redis away for a moment: try again next period
                    log.warning("build sweep failed: %s", e)

    thread = threading.Thread(target=sweeper, name="build-sweep", daemon=True)
    thread.start()
    worker = Worker([queue], connection=conn, name=f"posecell-{os.uname().nodename}-{os.getpid()}")
    try:
        worker.work(burst=burst, logging_level=settings.log_level.upper(), with_scheduler=False)
    finally:
        stop.set()
    return 0


def worker_status(settings: Settings) -> dict[str, Any]:
    conn = _connection(settings)
    queue = Queue(QUEUE_NAME, connection=conn)
    return {"queued": queue.count, "workers": Worker.count(queue=queue)}
