"""service.jobs.calibrations: the background calibration of a taught part, on both store backends (a real
Redis, as tests/test_store.py). The search itself (``pipeline.calibrate_appearance``) is replaced by one that
reports its photos and waits where told, so a stop, a change of the photos and a second process can be
put exactly between two photos; the real search through the API is tests/test_api_references.py's."""

from __future__ import annotations

import threading
from dataclasses import replace

import numpy as np
import pytest

from service import plane_calibrations, references
from service.jobs.calibrations import Calibrator, lease_key
from service.stores import open_store
from service.stores.base import Store
from service.vision import pipeline
from service.vision.model.appearance import Appearance
from tests.test_references import _reference

WRONG = 0.97  # the wrong score the stand-in search reports
LEASE_S = 2.0  # the calibration lease: a killed holder's runs out this fast here
STEP_S = 30.0  # how long the stand-in waits for a step before the test counts as hung


class Search:
    """Stands in for ``pipeline.calibrate_appearance``: tells ``progress`` before each photo, and on the
    photo ``hold`` (if any) waits for ``go``."""

    def __init__(self, hold: int | None = None) -> None:
        self.hold, self.go, self.reached, self.calls = hold, threading.Event(), threading.Event(), 0

    def __call__(self, bank, views, appearance, taught=None, progress=None):
        self.calls += 1
        for i in range(len(views)):
            progress(i, len(views))
            if i == self.hold:  # searching photo i
                self.reached.set()
                assert self.go.wait(STEP_S)
        return replace(appearance, wrong_score=WRONG, calibrated_photos=len(views))


@pytest.fixture
def calibratable(monkeypatch):
    """Every photo set teaches a calibratable appearance (coloured, photos agreeing)."""
    def teach(bank, views):
        return Appearance(np.full((len(bank.faces), 3), 100.0, np.float32), len(views), hue_share=0.2,
                          agreement=0.9 if len(views) > 1 else float("nan"))

    monkeypatch.setattr(pipeline, "teach_appearance", teach)
    references._TAUGHT.clear()
    yield
    references._TAUGHT.clear()


def _part(store: Store, bank, photos: int, wanted: bool = True) -> dict:
    store.create({"id": "m", "name": "part", "status": "ready", "created_at": "2024-01-01"}, b"mesh")
    store.put_bank("m", bank)
    for k in range(photos):
        store.add_reference("m", _reference(400.0 + 10 * k), references.MAX_REFERENCES)
    return store.update("m", calibration_wanted=wanted)


def _until(predicate, what: str) -> None:
    ok = threading.Event()
    for _ in range(int(STEP_S / 0.01)):
        if predicate():
            ok.set()
            break
        ok.wait(0.01)
    assert ok.is_set(), what


def test_a_calibration_runs_in_the_background_and_is_stored_for_its_photo_set(
        location, calibratable, l_block_bank, monkeypatch):
    search = Search(hold=1)
    monkeypatch.setattr(pipeline, "calibrate_appearance", search)
    with open_store(location) as store:
        record = _part(store, l_block_bank, 3)
        taught = references.appearance_of(store, record, l_block_bank)
        assert references.calibration_state(record, taught) == ("queued", 0.0)
        calibrator = Calibrator(store, LEASE_S)
        try:
            calibrator.submit("m")
            assert search.reached.wait(STEP_S)  # one photo searched, the second not yet
            status, progress = references.calibration_state(store.get("m"), taught)
            assert (status, progress) == ("running", pytest.approx(1 / 3))
            search.go.set()
            assert calibrator.wait("m", STEP_S)
        finally:
            calibrator.shutdown()
        done = store.get("m")
        assert done["calibration"] == {"references_version": record["references_version"], "photos": 3,
                                       "wrong_score": WRONG}
        assert references.calibration_state(done, taught) == ("calibrated", 1.0)
        assert not references.calibration_due(done)
        assert references.appearance_of(store, done, l_block_bank).wrong_score == WRONG


def test_a_calibration_stopped_by_a_shutdown_is_resumed_at_the_next_start(
        location, calibratable, l_block_bank, monkeypatch):
    search = Search(hold=1)
    monkeypatch.setattr(pipeline, "calibrate_appearance", search)
    with open_store(location) as store:
        record = _part(store, l_block_bank, 3)
        first = Calibrator(store, LEASE_S)
        first.submit("m")
        assert search.reached.wait(STEP_S)
        stopping = threading.Thread(target=first.shutdown)
        stopping.start()
        _until(lambda: first._closing, "the calibrator is stopping")
        search.go.set()  # the photo being searched ends; the next is not started
        stopping.join(STEP_S)
        stopped = store.get("m")
        assert "calibration" not in stopped and references.calibration_due(stopped)
        # the next start finds it due in the store, not in any memory, and calibrates it
        search.hold = None
        second = Calibrator(store, LEASE_S)
        try:
            assert second.resume() == ["m"]
            assert second.wait("m", STEP_S)
        finally:
            second.shutdown()
        assert store.get("m")["calibration"]["references_version"] == record["references_version"]
        assert search.calls == 2


def test_photos_changed_mid_calibration_stop_it_and_the_old_set_is_never_stored(
        location, calibratable, l_block_bank, monkeypatch):
    search = Search(hold=1)
    monkeypatch.setattr(pipeline, "calibrate_appearance", search)
    with open_store(location) as store, open_store(location) as other:
        _part(store, l_block_bank, 2)
        calibrator = Calibrator(store, LEASE_S)
        try:
            calibrator.submit("m")
            assert search.reached.wait(STEP_S)
            # another process adds a photo
            changed = other.add_reference("m", _reference(450.0), references.MAX_REFERENCES)
            search.go.set()
            assert calibrator.wait("m", STEP_S)
            now = store.get("m")
            assert "calibration" not in now and references.calibration_due(now)
            taught = references.appearance_of(store, now, l_block_bank)
            assert references.calibration_state(now, taught)[0] == "queued"  # its own POST queues it
            search.hold = None
            calibrator.submit("m")
            assert calibrator.wait("m", STEP_S)
        finally:
            calibrator.shutdown()
        assert store.get("m")["calibration"]["references_version"] == changed["references_version"]
        assert store.get("m")["calibration"]["photos"] == 3


def test_one_process_calibrates_a_photo_set_while_another_s_job_for_it_ends_at_once(
        location, calibratable, l_block_bank, monkeypatch):
    search = Search(hold=1)
    monkeypatch.setattr(pipeline, "calibrate_appearance", search)
    with open_store(location) as a, open_store(location) as b:
        _part(a, l_block_bank, 2)
        first, second = Calibrator(a, LEASE_S), Calibrator(b, LEASE_S)
        try:
            first.submit("m")
            assert search.reached.wait(STEP_S)
            second.submit("m")  # the lease is held by the first: nothing to do here
            assert second.wait("m", STEP_S)
            assert search.calls == 1
            search.go.set()
            assert first.wait("m", STEP_S)
        finally:
            first.shutdown()
            second.shutdown()
        assert search.calls == 1 and not references.calibration_due(a.get("m"))


def test_a_part_posted_without_calibrate_is_not_calibrated_nor_resumed(location, calibratable, l_block_bank,
                                                                        monkeypatch):
    search = Search()
    monkeypatch.setattr(pipeline, "calibrate_appearance", search)
    with open_store(location) as store:
        record = _part(store, l_block_bank, 2, wanted=False)
        taught = references.appearance_of(store, record, l_block_bank)
        assert references.calibration_state(record, taught) == ("not_requested", None)
        calibrator = Calibrator(store, LEASE_S)
        try:
            assert calibrator.resume() == []
        finally:
            calibrator.shutdown()
        assert search.calls == 0


def test_a_calibration_whose_process_was_killed_is_taken_over_once_its_lease_runs_out(
        location, calibratable, l_block_bank, monkeypatch):
    """A process killed mid-calibration leaves its lease behind, unrenewed: the restarted service's job
    finds it held, looks again every half lease, and calibrates once it has run out."""
    search = Search()
    monkeypatch.setattr(pipeline, "calibrate_appearance", search)
    with open_store(location) as store, open_store(location) as killed:
        record = _part(store, l_block_bank, 2)
        assert killed.try_lock(lease_key("m"), LEASE_S) is not None  # and then it died
        calibrator = Calibrator(store, LEASE_S)
        try:
            assert calibrator.resume() == ["m"]
            assert calibrator.wait("m", STEP_S)
            assert search.calls == 0 and references.calibration_due(store.get("m"))  # the lease is held
            _until(lambda: not references.calibration_due(store.get("m")), "taken over after the lease")
        finally:
            calibrator.shutdown()
        assert search.calls == 1
        assert store.get("m")["calibration"]["references_version"] == record["references_version"]


def test_a_plane_calibration_that_fails_is_kept_as_failed_and_not_tried_again(location, l_block_bank,
                                                                              monkeypatch):
    def broken(bank, scenes, progress=None):
        progress(0, scenes)
        raise RuntimeError("the rasteriser ran out of faces.")

    monkeypatch.setattr(plane_calibrations, "calibrate_plane", broken)
    with open_store(location) as store:
        store.create({"id": "m", "name": "part", "status": "ready", "created_at": "2024-01-01"}, b"mesh")
        store.put_bank("m", l_block_bank)
        assert plane_calibrations.plane_calibration_due(store.get("m"), 2)
        calibrator = Calibrator(store, LEASE_S, plane_scenes=2)
        try:
            calibrator.submit_plane(store.get("m"))
            assert calibrator.wait("m", STEP_S)
        finally:
            calibrator.shutdown()
        record = store.get("m")
        assert record["plane_calibration"]["status"] == "failed"
        assert record["plane_calibration"]["error"] == "the rasteriser ran out of faces"
        assert not plane_calibrations.plane_calibration_due(record, 2)  # resume and GET leave it
        warning = plane_calibrations.plane_calibration_warning(record)
        assert "failed (the rasteriser ran out of faces)" in warning
