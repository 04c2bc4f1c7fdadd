"""The local build pool: this service process's own build processes, one per model, at most
``POSE_BUILD_WORKERS`` at a time (the default with the diskcache store)."""

from __future__ import annotations

import collections
import logging
import os
import subprocess
import sys
import threading

from service.errors import sentence
from service.jobs.build import ACTIVE, MAX_BUILD_DEATHS, SHUTDOWN_GRACE_S, WORKER_CODE, child_env
from service.logs import json_level
from service.settings import Settings
from service.stores import open_store
from service.stores.base import Store

log = logging.getLogger("service")


class Builder:
    """The build processes of one service process (created and shut down by the app's lifespan).

    At most ``build_workers`` build processes run at once; further builds wait in a queue. Each
    process is watched by a thread that starts the next build when it ends, and re-queues a build
    whose process died (up to ``MAX_BUILD_DEATHS`` times, then the model is marked failed).
    """

    def __init__(self, settings: Settings) -> None:
        self.location = settings.store_location
        self.lease_s = float(settings.build_lease_s)
        self.workers = int(settings.build_workers)
        self.memory_mb = int(settings.build_memory_mb)
        self.threads = settings.threads
        self._cv = threading.Condition()
        self._queue: collections.deque[str] = collections.deque()
        self._running: dict[str, subprocess.Popen[bytes]] = {}
        self._cancelled: set[str] = set()
        self._deaths: dict[str, int] = {}  # build processes that died building each model
        self._closing = False
        self._env = child_env()

    def submit(self, mid: str) -> None:
        """Queue a build of ``mid`` unless this process already has one queued or running."""
        with self._cv:
            if self._closing or mid in self._running or mid in self._queue:
                return
            self._queue.append(mid)
            self._start_waiting()

    def resume(self, store: Store) -> list[str]:
        """Re-queue every build that was queued or running when the service last stopped."""
        ids = store.unfinished()
        for mid in ids:
            log.info("resuming the template build of model %s", mid)
            self.submit(mid)
        return ids

    def running(self) -> dict[str, int]:
        """Model id -> pid of each build process running now."""
        with self._cv:
            return {mid: p.pid for mid, p in self._running.items()}

    def cancel(self, mid: str) -> bool:
        """Drop ``mid``'s build: out of the queue, or its process killed now (its memory freed with it).

        For a deleted model; True if a build process was running."""
        with self._cv:
            if mid in self._queue:
                self._queue.remove(mid)
            proc = self._running.get(mid)
            if proc is None:
                return False
            self._cancelled.add(mid)
        proc.kill()
        return True

    def _start_waiting(self) -> None:  # with self._cv held
        while self._queue and len(self._running) < self.workers and not self._closing:
            mid = self._queue.popleft()
            cmd = [sys.executable, "-c", WORKER_CODE, self.location, mid, repr(self.lease_s),
                   str(os.getpid()), str(self.memory_mb), json_level() or "",
                   "" if self.threads is None else str(self.threads)]
            proc = subprocess.Popen(cmd, env=self._env, stdin=subprocess.DEVNULL)
            self._running[mid] = proc
            threading.Thread(target=self._watch, args=(mid, proc), name=f"build-{mid}", daemon=True).start()

    def _watch(self, mid: str, proc: subprocess.Popen[bytes]) -> None:
        code = proc.wait()
        with self._cv:
            self._running.pop(mid, None)
            cancelled = mid in self._cancelled
            self._cancelled.discard(mid)
            closing = self._closing
            self._cv.notify_all()
        if not (closing or cancelled or code == 0):
            self._died(mid, code)
        with self._cv:
            self._start_waiting()

    def _died(self, mid: str, code: int) -> None:
        log.error("template build process for model %s died (exit status %s)", mid, code)
        self._deaths[mid] = self._deaths.get(mid, 0) + 1
        with open_store(self.location) as store:
            rec = store.get(mid)
            if rec is None or rec["status"] not in ACTIVE:
                return
            if self._deaths[mid] < MAX_BUILD_DEATHS:
                self.submit(mid)
            else:
                store.update(mid, status="failed", error=sentence(
                    f"The build process died {MAX_BUILD_DEATHS} times (out of memory? its limit is "
                    f"{self.memory_mb:,} MB, POSE_BUILD_MEMORY_MB); use a coarser template grid or a smaller "
                    "mesh, or raise the limit"))

    def shutdown(self) -> None:
        """Stop building now: running builds go back to "queued" and resume at the next start-up."""
        with self._cv:
            self._closing = True
            self._queue.clear()
            procs = list(self._running.values())
        for p in procs:  # a building process puts its model back to "queued" and exits (run_build)
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(timeout=SHUTDOWN_GRACE_S)
            except subprocess.TimeoutExpired:  # its lease stays until it expires; the build resumes later
                p.kill()
                p.wait(timeout=5)
