"""Calibrations of parts' operating points, in the background of the API process: a taught part's on its
reference photos, and every part's on a plane on rendered scenes of it (``service/plane_calibrations``).

``POST /models/{id}/references`` stores a photo and marks the record ``calibration_wanted``; calibrating
(``references.calibrate_stored``: a search per stored photo, seconds each) would hold the request for half
a minute with a dozen photos. So the POST hands the model to the process's ``Calibrator`` and answers at
once; GET shows ``calibration_status`` and its progress, written to the record before each photo::

    posted -> queued -> running (progress) -> calibrated

What to calibrate is read from the record, never kept only in memory: a calibration is due while the
record wants one and holds none of its current photo set (``references.calibration_due``). A stop or a
crash mid-calibration therefore loses only the photos searched so far: every start-up re-queues the due
models (``resume``). A calibration whose photos change under it (another POST, a DELETE, in any process)
stops at its next photo; the change's own POST queues the new set. Across processes the model's
calibration lease (the store's build lease under ``<id>:calibration``, ``Settings.build_lease_s``,
renewed before every photo) lets one process calibrate a set; another process's job for it looks again
every half lease while the set is still due, so a calibration whose process was killed is taken over
once its lease runs out.

A part's plane calibration is due once its templates are ready (``plane_calibration_due``): ``GET
/models``, ``GET /models/{id}`` and an estimate of the part queue it (``submit_plane``), as every start-up
does; it keeps its progress and result in the record, under its own lease (``<id>:plane_calibration``).
"""

from __future__ import annotations

import collections
import logging
import threading
from typing import Any

from service.errors import clause
from service.plane_calibrations import calibrate_plane_stored, plane_calibration_due, plane_calibration_failed
from service.references import calibrate_stored, calibration_due
from service.stores.base import Store

log = logging.getLogger("service")

STOP_WAIT_S = 10.0  # a stopping service waits this long for the photo being searched


class _StoppedError(Exception):
    """Raised from the progress callback: the service is stopping or the photos changed."""


def lease_key(mid: str) -> str:
    return f"{mid}:calibration"


def plane_lease_key(mid: str) -> str:
    return f"{mid}:plane_calibration"


class Calibrator:
    """One background thread calibrating the models handed to it, one at a time, in order."""

    def __init__(self, store: Store, lease_s: float, plane_scenes: int = 0) -> None:
        self.store, self.lease_s = store, float(lease_s)  # a photo's search takes seconds: well under it
        self.plane_scenes = int(plane_scenes)  # rendered scenes a plane calibration judges (0: none)
        self._retries: dict[str, threading.Timer] = {}
        self._cv = threading.Condition()
        self._queue: collections.deque[str] = collections.deque()
        self._current: str | None = None
        self._closing = False
        self._thread = threading.Thread(target=self._work, name="calibrations", daemon=True)
        self._thread.start()

    def submit(self, mid: str) -> None:
        """Queue a calibration of ``mid``'s current photos unless one is already queued here."""
        with self._cv:
            if not self._closing and mid not in self._queue:
                self._queue.append(mid)
                self._cv.notify_all()

    def submit_plane(self, record: dict[str, Any]) -> None:
        """Queue the record's plane calibration if it is due (``plane_calibration_due``)."""
        if plane_calibration_due(record, self.plane_scenes):
            self.submit(record["id"])

    def resume(self) -> list[str]:
        """Queue every model whose record wants a calibration it does not hold (a stop or crash ended it)."""
        due = [r["id"] for r in self.store.records() if r.get("status") == "ready" and (
            calibration_due(r) or plane_calibration_due(r, self.plane_scenes))]
        for mid in due:
            log.info("resuming the calibration of model %s", mid)
            self.submit(mid)
        return due

    def wait(self, mid: str, timeout_s: float | None = None) -> bool:
        """Block until this process has no calibration of ``mid`` queued or running; False on timeout."""
        with self._cv:
            return self._cv.wait_for(lambda: mid not in self._queue and self._current != mid, timeout_s)

    def shutdown(self) -> None:
        """Stop after the photo being searched; what is left stays due in the store for the next start."""
        with self._cv:
            self._closing = True
            self._queue.clear()
            for timer in self._retries.values():
                timer.cancel()
            self._cv.notify_all()
        self._thread.join(STOP_WAIT_S)

    def _work(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._queue or self._closing)
                if self._closing:
                    return
                self._current = self._queue.popleft()
            try:
                self._calibrate(self._current)
            except Exception:  # a failed calibration leaves the part at the global operating point
                log.exception("the calibration of model %s failed", self._current)
            finally:
                with self._cv:
                    self._current = None
                    self._cv.notify_all()

    def _calibrate(self, mid: str) -> None:
        self._calibrate_references(mid)
        self._calibrate_plane(mid)

    def _calibrate_plane(self, mid: str) -> None:
        record = self.store.get(mid)
        if record is None or not plane_calibration_due(record, self.plane_scenes):
            return
        token = self.store.try_lock(plane_lease_key(mid), self.lease_s)
        if token is None:
            self._retry_later(mid)
            return
        try:
            bank = self.store.bank(mid)
            if bank is None:
                return

            def progress(done: int, total: int) -> None:
                if self._closing or self.store.get(mid) is None:
                    raise _StoppedError
                self.store.renew(plane_lease_key(mid), token, self.lease_s)

            calibrate_plane_stored(self.store, mid, bank, self.plane_scenes, progress)
            log.info("calibrated model %s on a plane (%d rendered scenes)", mid, self.plane_scenes)
        except _StoppedError:
            log.info("the plane calibration of model %s stopped (deleted or service stopping)", mid)
        except Exception as e:  # kept as failed: the part is judged without it, and not tried again
            log.exception("the plane calibration of model %s failed", mid)
            plane_calibration_failed(self.store, mid, clause(str(e)) or type(e).__name__)
        finally:
            self.store.unlock(plane_lease_key(mid), token)

    def _calibrate_references(self, mid: str) -> None:
        record = self.store.get(mid)
        if record is None or record.get("status") != "ready" or not calibration_due(record):
            return
        bank = self.store.bank(mid)
        token = self.store.try_lock(lease_key(mid), self.lease_s)
        if token is None:  # another process calibrates them (or died doing so: its lease runs out)
            self._retry_later(mid)
            return
        if bank is None:
            self.store.unlock(lease_key(mid), token)
            return
        version = record.get("references_version")

        def progress(done: int, total: int) -> None:
            current = self.store.get(mid)
            if self._closing or current is None or current.get("references_version") != version:
                raise _StoppedError
            self.store.renew(lease_key(mid), token, self.lease_s)
            self.store.update(mid, calibration_progress=_progress(version, done, total))

        try:
            calibrate_stored(self.store, record, bank, progress)
            log.info("calibrated model %s on its reference photos", mid)
        except _StoppedError:
            log.info("the calibration of model %s stopped (photos changed or service stopping)", mid)
        finally:
            self.store.unlock(lease_key(mid), token)

    def _retry_later(self, mid: str) -> None:
        with self._cv:
            if self._closing or mid in self._retries:
                return
            timer = threading.Timer(self.lease_s / 2, self._retry, args=(mid,))
            timer.daemon = True
            self._retries[mid] = timer
            timer.start()

    def _retry(self, mid: str) -> None:
        with self._cv:
            self._retries.pop(mid, None)
        self.submit(mid)


def _progress(version: Any, done: int, total: int) -> dict[str, Any]:
    return {"references_version": version, "done": int(done), "total": int(total)}
