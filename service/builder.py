"""Template builds: registering an upload, and building its template bank off the event loop.

An upload is decoded once (bad files fail at once with 415/422), registered under its content id
with status ``queued``, and handed to the ``Builder``: a process pool (spawn) owned by the app's
lifespan. ``run_build`` runs in a pool process, opens its own ``Store`` on the shared cache dir and
takes the model's build lease, so across all service processes a model is built once::

    queued -> building -> ready | failed

Progress (0..1) is written to the record every ``PROGRESS_STEP``. A build that was interrupted
(process stopped or killed) stays ``queued``/``building``; at start-up every service process
re-queues those, the first to get the lease builds and the others wait for it to finish. A lease
whose process died expires after ``Settings.build_lease_s``, and the build is taken over.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import threading
import time
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from service.decode import decode_mesh
from service.errors import UnprocessableError, clause, sentence
from service.logs import configure_like, json_level
from service.settings import Settings
from service.store import Store, model_id
from service.vision.bank import TemplateBank

log = logging.getLogger("service")

PROGRESS_STEP = 0.02  # write progress at most every 2 %
LEASE_POLL_S = 0.5  # how often a process waiting for another's build looks again
SHUTDOWN_GRACE_S = 5.0  # a stopping service waits this long for a build process to put its model back
MAX_BUILD_DEATHS = 3  # a build whose process keeps dying (OOM) is marked failed after this many


def register_upload(store: Store, settings: Settings, data: bytes, *, filename: str, name: str | None = None,
                    units: str = "mm", symmetry: str = "auto",
                    templates: dict[str, Any] | None = None) -> tuple[dict[str, Any], bool]:
    """Validate and store an uploaded mesh: ``(record, needs_build)``.

    Idempotent: the same bytes with the same options give the same id and the existing record
    (a failed model is queued again: uploading it again is how a client retries). ``templates``
    overrides ``settings.template_grid`` key by key; the record keeps exactly what was asked for
    (the vision code tells an explicit option from a default).
    """
    from service.vision.build.grid import merge_grid

    grid = {**settings.template_grid, **(templates or {})}
    try:  # bad options fail the upload now (422), not the build later
        merge_grid(grid)
    except ValueError as e:
        raise UnprocessableError(f"The templates options are invalid: {clause(e)}; fix them and upload "
                                 "again") from e
    mid = model_id(data, units=units, symmetry=symmetry, templates=grid)
    existing = store.get(mid)
    if existing is None:
        mesh = decode_mesh(data, filename, units)  # raises 415/422 now, not in the build
        record = {
            "id": mid, "name": name or filename, "filename": filename, "units": units,
            "symmetry_option": symmetry, "templates": grid,
            "status": "queued", "progress": 0.0, "error": None, "n_templates": None,
            "extents_mm": [float(x) for x in mesh.extents],
            "symmetry": symmetry_of_option(symmetry),
            "created_at": datetime.now(UTC).isoformat(),
        }
        if store.create(record, data):
            return record, True
        existing = store.get(mid)  # another process registered it a moment ago
    if existing is not None and existing["status"] == "failed":
        return store.update(mid, status="queued", progress=0.0, error=None) or existing, True
    return existing or {}, False


_AXES = {"x": [1.0, 0.0, 0.0], "y": [0.0, 1.0, 0.0], "z": [0.0, 0.0, 1.0]}


def symmetry_of_option(option: str) -> dict[str, Any] | None:
    """The record's ``symmetry`` as an upload's ``symmetry`` option already says it (the wire form of
    ``schemas.Symmetry``); None for "auto": known after the build."""
    if option == "none":
        return {"type": "none", "axis": None}
    if option in _AXES:
        return {"type": "continuous", "axis": list(_AXES[option])}
    return None


def symmetry_of_bank(bank: TemplateBank) -> dict[str, Any]:
    """The record's ``symmetry`` as the build found it."""
    if bank.symmetry_axis_obj is None:
        return {"type": "none", "axis": None}
    return {"type": "continuous", "axis": [float(x) for x in bank.symmetry_axis_obj]}


class _DeletedError(Exception):
    """The model was deleted while it was being built."""


def run_build(cache_dir: str, mid: str, lease_s: float) -> str:
    """Build model ``mid``'s template bank (in a pool process, or in-process for the CLI).

    Returns the final status: "ready", "failed" or "deleted". A SIGTERM while building puts the
    model back to "queued" (it resumes at the next start-up), releases the lease and ends the
    process at once (status 143). That is done by the lease's heartbeat thread, not by unwinding the
    main thread: the main thread may be waiting on a thread pool that would first render every
    remaining view, longer than the stopping service waits before it kills the process, which
    would leave the model "building" until its lease ran out.
    """
    from service.pipeline import build_templates

    store = Store(cache_dir)
    token: str | None = None
    wake = threading.Event()  # the heartbeat stops renewing: the build ended, or a SIGTERM came
    sigterm = threading.Event()
    heartbeat: threading.Thread | None = None

    def on_sigterm(signum: int, frame: object) -> None:
        if heartbeat is None:  # no lease taken yet: nothing to put back
            raise SystemExit(128 + signum)
        sigterm.set()
        wake.set()

    in_main = threading.current_thread() is threading.main_thread()
    old_handler = signal.signal(signal.SIGTERM, on_sigterm) if in_main else None
    try:
        while True:  # wait for the lease, unless the build gets done or deleted meanwhile
            rec = store.get(mid)
            if rec is None:
                return "deleted"
            if rec["status"] in ("ready", "failed"):
                return rec["status"]
            if token is not None:
                break
            token = store.try_lock(mid, lease_s)
            if token is None:
                time.sleep(LEASE_POLL_S)

        def renew(token: str = token) -> None:
            while not wake.wait(lease_s / 3):
                store.renew(mid, token, lease_s)
            if sigterm.is_set():
                store.update(mid, status="queued")
                store.unlock(mid, token)
                log.info("template build of model %s stopped; it resumes at the next start-up", mid)
                os._exit(128 + signal.SIGTERM)

        heartbeat = threading.Thread(target=renew, name=f"lease-{mid}", daemon=True)
        heartbeat.start()
        store.count_build(mid)
        store.update(mid, status="building", progress=0.0, error=None)
        last = [0.0]

        def progress(fraction: float) -> None:
            f = min(max(float(fraction), 0.0), 1.0)
            if f - last[0] >= PROGRESS_STEP or (f >= 1.0 > last[0]):
                last[0] = f
                if store.update(mid, progress=f) is None:
                    raise _DeletedError(mid)

        try:
            mesh = decode_mesh(store.mesh(mid) or b"", rec["filename"], rec["units"])
            bank = build_templates(mesh, symmetry=rec["symmetry_option"], grid=dict(rec["templates"]),
                                   progress=progress)
        except _DeletedError:
            return "deleted"
        except Exception as e:
            log.exception("template build of model %s failed", mid)
            reason = sentence(getattr(e, "detail", None) or clause(e) or type(e).__name__)
            return "failed" if store.update(mid, status="failed", error=reason) is not None else "deleted"
        store.put_bank(mid, bank)
        done = store.update(mid, status="ready", progress=1.0, error=None, n_templates=bank.n_templates,
                            extents_mm=[float(x) for x in bank.extents_mm],
                            symmetry=symmetry_of_bank(bank))
        if done is None:  # deleted while we stored the bank: leave nothing behind
            store.delete(mid)
            return "deleted"
        return "ready"
    except (SystemExit, KeyboardInterrupt):
        if token is not None:
            store.update(mid, status="queued")
        raise
    finally:
        wake.set()
        if heartbeat is not None:
            heartbeat.join()
        if token is not None:
            store.unlock(mid, token)
        store.close()
        if in_main:
            signal.signal(signal.SIGTERM, old_handler)


def _start_build_process(log_level: str | None, threads_budget: int | None) -> None:
    """A build process logs like its parent and keeps to the service's thread budget."""
    from service.vision import threads

    configure_like(log_level)
    threads.configure(threads_budget)


class Builder:
    """The build executor of one service process (created and shut down by the app's lifespan)."""

    def __init__(self, settings: Settings) -> None:
        self.cache_dir = str(Path(settings.cache_dir))
        self.lease_s = float(settings.build_lease_s)
        self.workers = int(settings.build_workers)
        self.threads = settings.threads
        self._lock = threading.Lock()
        self._futures: dict[str, Future[str]] = {}
        self._deaths: dict[str, int] = {}  # pool processes that died building each model
        self._closing = False
        self._executor = self._new_executor()

    def _new_executor(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(max_workers=self.workers, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_start_build_process, initargs=(json_level(), self.threads))

    def submit(self, mid: str) -> None:
        """Queue a build of ``mid`` unless this process already has one queued or running."""
        with self._lock:
            if self._closing:
                return
            fut = self._futures.get(mid)
            if fut is not None and not fut.done():
                return
            fut = self._executor.submit(run_build, self.cache_dir, mid, self.lease_s)
            self._futures[mid] = fut
        fut.add_done_callback(lambda f, mid=mid: self._finished(mid, f))

    def resume(self, store: Store) -> list[str]:
        """Re-queue every build that was queued or running when the service last stopped."""
        ids = store.unfinished()
        for mid in ids:
            log.info("resuming the template build of model %s", mid)
            self.submit(mid)
        return ids

    def _finished(self, mid: str, fut: Future[str]) -> None:
        if fut.cancelled() or self._closing:
            return
        exc = fut.exception()
        if exc is None:
            log.info("template build of model %s: %s", mid, fut.result())
            return
        log.error("template build process for model %s died: %r", mid, exc)
        if not isinstance(exc, BrokenProcessPool):
            return
        with self._lock:  # a dead worker breaks the pool for good; later builds need a new one
            if self._closing:
                return
            if self._executor._broken:  # no public flag for this in 3.11
                self._executor = self._new_executor()
        self._deaths[mid] = self._deaths.get(mid, 0) + 1
        with Store(self.cache_dir) as store:
            rec = store.get(mid)
            if rec is None or rec["status"] not in ("queued", "building"):
                return
            if self._deaths[mid] < MAX_BUILD_DEATHS:
                self.submit(mid)
            else:
                store.update(mid, status="failed", error=sentence(
                    f"The build process died {MAX_BUILD_DEATHS} times (out of memory?); use a coarser "
                    "template grid or a smaller mesh"))

    def shutdown(self) -> None:
        """Stop building now: running builds go back to "queued" and resume at the next start-up."""
        with self._lock:
            self._closing = True
            executor = self._executor
        # Python 3.11 has no ProcessPoolExecutor.terminate_workers(): cancel what waits, stop the
        # processes, then let the pool wind down (joining its queues) once they are gone.
        procs = list((getattr(executor, "_processes", None) or {}).values())
        for fut in list(self._futures.values()):
            fut.cancel()
        for p in procs:
            if p.is_alive():
                p.terminate()
        for p in procs:  # a building process puts its model back to "queued" and exits (run_build)
            p.join(timeout=SHUTDOWN_GRACE_S)
            if p.is_alive():  # its lease stays until it expires; the build resumes at the next start-up
                p.kill()
                p.join(timeout=5)
        executor.shutdown(wait=True, cancel_futures=True)
