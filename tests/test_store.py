"""Store: content ids, records shared across Store instances (processes), banks, build leases, delete.

The contract tests run on both backends: the diskcache directory and a real Redis (tests/redis_server.py)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from service.errors import ConflictError
from service.stores import open_store
from service.stores.base import bank_from_bytes, bank_to_bytes, model_id
from service.vision.bank import TemplateBank

MESH = b"solid fake mesh bytes"


def _bank(n: int = 3, symmetric: bool = True) -> TemplateBank:
    rng = np.random.default_rng(3)
    counts = np.array([4, 5, 6][:n])
    p = int(counts.sum())
    return TemplateBank(
        R_tpl_obj=np.repeat(np.eye(3)[None], n, axis=0), view_params_deg=rng.random((n, 2)),
        offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        xy_n=rng.random((p, 2)).astype(np.float32), theta_rad=rng.random(p).astype(np.float32),
        p_obj=rng.random((p, 3)).astype(np.float32), centre_obj=np.array([0.0, 100.0, 0.0]),
        reference_distance_mm=500.0, vertices_mm=rng.random((8, 3)).astype(np.float32),
        faces=np.array([[0, 1, 2], [2, 3, 4]], np.int32), extents_mm=np.array([60.0, 200.0, 60.0]),
        diameter_mm=201.9, symmetry_axis_obj=np.array([0.0, 1.0, 0.0]) if symmetric else None,
        symmetry_point_obj=np.zeros(3) if symmetric else None, grid={"tilt_step_deg": 15},
    )


def _record(mid: str, status: str = "queued", created_at: str = "2024-01-01T00:00:00+00:00") -> dict:
    return {"id": mid, "name": "part.stl", "status": status, "progress": 0.0, "created_at": created_at}


@pytest.fixture
def store(location):
    with open_store(location) as s:
        yield s


def test_model_id_is_a_content_hash_of_bytes_and_options():
    base = model_id(MESH, units="mm", symmetry="auto", templates={"tilt_step_deg": 15})
    assert base == model_id(MESH, units="mm", symmetry="auto", templates={"tilt_step_deg": 15.0})
    assert len(base) >= 16 and all(c in "0123456789abcdef" for c in base)
    others = {
        model_id(MESH + b" ", units="mm", symmetry="auto", templates={"tilt_step_deg": 15}),
        model_id(MESH, units="cm", symmetry="auto", templates={"tilt_step_deg": 15}),
        model_id(MESH, units="mm", symmetry="y", templates={"tilt_step_deg": 15}),
        model_id(MESH, units="mm", symmetry="auto", templates={"tilt_step_deg": 10}),
        model_id(MESH, units="mm", symmetry="auto", templates={}),
    }
    assert base not in others and len(others) == 5


def test_records_are_shared_between_store_instances(location):
    with open_store(location) as a, open_store(location) as b:
        assert a.create(_record("m1"), MESH)
        assert not b.create(_record("m1"), b"other")  # the id exists: first upload wins
        assert b.get("m1")["status"] == "queued" and b.mesh("m1") == MESH
        b.update("m1", status="building", progress=0.5)
        assert a.get("m1")["progress"] == 0.5 and a.get("m1")["name"] == "part.stl"
        assert a.update("missing", status="ready") is None


def test_list_and_unfinished(store):
    store.create(_record("b", "ready", "2024-01-02T00:00:00+00:00"), MESH)
    store.create(_record("a", "queued", "2024-01-01T00:00:00+00:00"), MESH)
    store.create(_record("c", "building", "2024-01-03T00:00:00+00:00"), MESH)
    assert [r["id"] for r in store.records()] == ["a", "b", "c"]
    assert sorted(store.unfinished()) == ["a", "c"]


def test_bank_round_trip_and_lru(store):
    bank = _bank()
    again = bank_from_bytes(bank_to_bytes(bank))
    for name in ("R_tpl_obj", "offsets", "xy_n", "theta_rad", "p_obj", "faces", "symmetry_axis_obj"):
        np.testing.assert_array_equal(getattr(again, name), getattr(bank, name))
    assert again.grid == bank.grid and again.n_templates == 3
    assert bank_from_bytes(bank_to_bytes(_bank(symmetric=False))).symmetry_axis_obj is None

    assert store.bank("m") is None
    store.put_bank("m", bank)
    first = store.bank("m")
    assert first is store.bank("m")  # loaded once, then served from memory
    assert first.n_templates == bank.n_templates


def test_delete_removes_every_record(store, location):
    store.create(_record("m"), MESH)
    store.put_bank("m", _bank())
    store.count_build("m")
    assert store.bank("m") is not None
    assert store.delete("m")
    assert store.get("m") is None and store.mesh("m") is None and store.bank("m") is None
    assert store.build_count("m") == 0 and list(store.ids()) == []
    assert not store.delete("m")
    with open_store(location) as other:  # nothing is left in the store either
        assert other.bank("m") is None


def test_build_lease_is_exclusive_renewable_and_expires(location):
    with open_store(location) as a, open_store(location) as b:
        token = a.try_lock("m", lease_s=60)
        assert token is not None and a.lock_holder("m") == token
        assert b.try_lock("m", lease_s=60) is None
        assert a.renew("m", token, lease_s=60) and not b.renew("m", "not-the-holder", lease_s=60)
        b.unlock("m", "not-the-holder")  # only the holder can release it
        assert a.lock_holder("m") == token
        a.unlock("m", token)
        short = b.try_lock("m", lease_s=0.05)
        assert short is not None
        time.sleep(0.2)  # the holder "died": its lease runs out and anyone may take over
        assert a.try_lock("m", lease_s=60) is not None


def test_build_counter(store):
    assert store.build_count("m") == 0
    assert store.count_build("m") == 1 and store.count_build("m") == 2
    assert store.build_count("m") == 2


def test_a_rebuilt_bank_replaces_every_process_s_loaded_copy(location):
    with open_store(location) as api, open_store(location) as builder:
        builder.put_bank("m", _bank(3))
        assert api.bank("m").n_templates == 3
        builder.put_bank("m", _bank(2))  # rebuilt elsewhere: a new version
        assert api.bank("m").n_templates == 2
        builder.delete("m")  # deleted elsewhere
        assert api.bank("m") is None


def test_grasps_and_cameras(store):
    assert store.grasps("m") == [] and store.cameras() == []
    store.put_grasps("m", [{"name": "top", "T_obj_grasp": {"R": [[1, 0, 0]], "t_mm": [0, 1, 2]}}])
    assert store.grasps("m")[0]["name"] == "top"
    assert store.put_camera("b", {"fx": 1.0}) and store.put_camera("a", {"fx": 2.0})
    assert not store.put_camera("a", {"fx": 3.0})  # replaced
    assert store.cameras() == [("a", {"fx": 3.0}), ("b", {"fx": 1.0})]
    assert store.delete_camera("a") and not store.delete_camera("a") and store.camera("a") is None


def _reference(k: int) -> dict:
    return {"image": bytes([k, 0, 255]) * 1000, "camera": {"fx": 500.0 + k, "fy": 500.0, "cx": 319.5,
                                                          "cy": 239.5},
            "camera_name": None, "T_cam_obj": {"R": np.eye(3).tolist(), "t_mm": [0.0, 0.0, 400.0 + k]},
            "width": 640, "height": 480}


def _described(ref: dict) -> dict:
    return {k: v for k, v in ref.items() if k != "image"}


def test_reference_photos_round_trip_bounded_and_survive_a_restart(location):
    with open_store(location) as store:
        store.create(_record("m", "ready"), MESH)
        assert store.references("m") == [] and store.get("m").get("references") is None
        first = store.add_reference("m", _reference(0), limit=2)
        assert first["references"] == 1 and store.get("m") == first
        second = store.add_reference("m", _reference(1), limit=2)
        assert second["references"] == 2 and second["references_version"] != first["references_version"]
        with pytest.raises(ConflictError) as full:
            store.add_reference("m", _reference(2), limit=2)
        assert "already has 2 reference photos" in full.value.detail and "DELETE" in full.value.detail
        assert store.get("m") == second  # nothing of the refused photo was kept
        assert store.references("m") == [_described(_reference(0)), _described(_reference(1))]
        assert store.add_reference("gone", _reference(0), limit=2) is None
    with open_store(location) as store:  # reopened (a restart, or another process): the photos are there
        assert store.references("m", images=True) == [_reference(0), _reference(1)]
        assert store.get("m")["references"] == 2
        cleared = store.clear_references("m")
        assert cleared["references"] == 0 and cleared["references_version"] != second["references_version"]
        assert store.references("m", images=True) == [] and store.get("m") == cleared
        assert store.add_reference("m", _reference(3), limit=2)["references"] == 1
        assert store.clear_references("gone") is None


def test_deleting_a_model_deletes_its_reference_photos(store, location):
    store.create(_record("m", "ready"), MESH)
    store.add_reference("m", _reference(0), limit=12)
    assert store.delete("m")
    assert store.references("m", images=True) == []
    store.create(_record("m", "ready"), MESH)  # uploaded again: it starts untaught
    assert store.references("m") == [] and store.get("m").get("references") is None
    if not location.startswith("redis"):
        assert not any(str(k).startswith("ref") for k in store._cache.iterkeys())


def test_update_if_keeps_a_finished_status(store):
    store.create(_record("m", "ready"), MESH)
    assert store.update_if("m", ("queued", "building"), status="queued") is None
    assert store.get("m")["status"] == "ready"
    assert store.update_if("m", ("ready",), progress=1.0)["progress"] == 1.0


def test_the_bank_cache_is_bounded_in_megabytes():
    from service.stores.base import BankCache, bank_nbytes

    bank = _bank()
    cache = BankCache(max_mb=2.5 * bank_nbytes(bank) / (1024 * 1024))
    for mid in ("a", "b", "c"):
        cache.put(mid, "v1", bank)
    assert cache.get("a", "v1") is None and cache.get("c", "v1") is bank  # least recently used went first
    assert cache.get("c", "v2") is None  # another version is another bank


def test_a_large_bank_is_stored_in_chunks(redis_url, monkeypatch):
    import redis

    from service.stores import redis as redis_store

    monkeypatch.setattr(redis_store, "CHUNK_BYTES", 1000)
    with open_store(redis_url) as s:
        bank = _bank()
        s.put_bank("m", bank)
        with redis.Redis.from_url(redis_url) as r:
            version = r.get("posecell:v1:bank:m").decode()
            assert r.llen(f"posecell:v1:bank:m:{version}") > 1
        with open_store(redis_url) as other:
            np.testing.assert_array_equal(other.bank("m").xy_n, bank.xy_n)


def test_an_unreachable_redis_is_a_503_sentence_not_a_crash():
    from service.errors import StoreUnavailableError
    from tests.redis_server import free_port

    with open_store(f"redis://127.0.0.1:{free_port()}/0") as s:
        assert "cannot be reached" in s.ping()
        with pytest.raises(StoreUnavailableError) as e:
            s.get("m")
        assert e.value.status_code == 503 and e.value.detail.endswith(".")


def test_a_bank_written_before_banks_had_versions_still_loads(tmp_path):
    import diskcache

    with diskcache.Cache(str(tmp_path / "old")) as old:  # a cache volume as the last release left it
        old.set("bank:m", bank_to_bytes(_bank()))
    with open_store(tmp_path / "old") as s:
        assert s.bank("m").n_templates == 3
        s.put_bank("m", _bank(2))  # rebuilt: versioned from now on
        assert s.bank("m").n_templates == 2
