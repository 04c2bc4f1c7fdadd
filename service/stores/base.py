"""The store: model records, uploaded meshes, template banks, build status and leases, grasps, cameras,
reference photos.

``Store`` is the interface every layer above uses; two backends implement it, chosen by one setting
(``POSE_STORE``) and unknown to everything above the ``service.stores`` package:

    service/stores/disk.py   ``DiskStore``: diskcache in ``POSE_CACHE_DIR`` (the default; one machine,
                             several processes share it through SQLite)
    service/stores/redis.py  ``RedisStore``: ``POSE_STORE=redis://host:6379/0`` (many API replicas and
                             build workers on one Redis; key names documented there)

``open_store(location)`` (``service/stores/__init__.py``) opens the backend the location names (a
``redis://``/``rediss://``/``unix://`` URL, else a cache directory). Logical records, for a model id
``<id>``::

    model:<id>    record (dict): name, units, options, status, progress, error, extents, ...
    mesh:<id>     the uploaded mesh bytes, exactly as sent
    bank:<id>     the template bank, ``np.savez`` of ``TemplateBank.to_arrays()``, and its version
    lock:<id>     build lease: the token of the process building <id>; expires unless renewed
    builds:<id>   how many times a build of <id> has started (a crash-resumed build counts twice)
    grasps:<id>   the model's grasps (list of dicts, as PUT /models/{id}/grasps sent them)
    camera:<name> a registered camera (dict: intrinsics, image size, extrinsics, plane)
    refs:<id>     the model's reference photos (``service.references``): per photo the image bytes as
                  uploaded, its camera (resolved intrinsics), ``T_cam_obj`` and image size; the record
                  counts them (``references``) and names their set (``references_version``, new at
                  every change: what each process's taught-appearance memo is keyed by)

Ids are content hashes (``model_id``): the same mesh bytes with the same options give the same id.
Each process keeps the banks it loaded in a ``BankCache`` bounded in MB (``POSE_BANK_CACHE_MB``).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import socket
import threading
import uuid
from collections import OrderedDict
from collections.abc import Iterator
from typing import Any

import numpy as np

from service.errors import BuildFailedError, ConflictError, NotReadyError, clause
from service.vision.bank import TemplateBank

ID_HEX_CHARS = 20
DEFAULT_BANK_CACHE_MB = 256  # banks kept loaded per process (POSE_BANK_CACHE_MB)
REDIS_SCHEMES = ("redis://", "rediss://", "unix://")


def _number(v: Any) -> Any:
    """Normalise JSON options so 15 and 15.0 hash alike."""
    if isinstance(v, bool):
        return v
    if isinstance(v, int | float):
        return float(v)
    if isinstance(v, dict):
        return {str(k): _number(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_number(x) for x in v]
    return v


def normalise_options(options: dict[str, Any]) -> dict[str, Any]:
    return _number(options)


def model_id(mesh: bytes, *, units: str, symmetry: str, templates: dict[str, Any]) -> str:
    """sha256 of the mesh bytes and the normalised build options, first ``ID_HEX_CHARS`` hex chars."""
    h = hashlib.sha256(mesh)
    opts = {"units": units, "symmetry": symmetry, "templates": normalise_options(templates)}
    h.update(b"\0" + json.dumps(opts, sort_keys=True, separators=(",", ":")).encode())
    return h.hexdigest()[:ID_HEX_CHARS]


def bank_to_bytes(bank: TemplateBank) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **bank.to_arrays())
    return buf.getvalue()


def bank_from_bytes(data: bytes) -> TemplateBank:
    with np.load(io.BytesIO(data), allow_pickle=False) as a:
        return TemplateBank.from_arrays(a)


def is_shared(location: str | os.PathLike[str]) -> bool:
    """True when ``location`` names a Redis server (the shared store), False for a cache directory."""
    return str(location).startswith(REDIS_SCHEMES)


def bank_nbytes(bank: TemplateBank) -> int:
    return int(sum(np.asarray(a).nbytes for a in bank.to_arrays().values()))


class BankCache:
    """The banks this process has loaded, least recently used dropped first, at most ``max_mb`` MB.

    Entries are keyed by model id and carry the bank's version: a bank rebuilt or deleted anywhere
    has a new version (or none), so a stale entry is never served."""

    def __init__(self, max_mb: float = DEFAULT_BANK_CACHE_MB) -> None:
        self.max_bytes = int(max_mb * 1024 * 1024)
        self._items: OrderedDict[str, tuple[str, TemplateBank, int]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, mid: str, version: str) -> TemplateBank | None:
        with self._lock:
            item = self._items.get(mid)
            if item is None or item[0] != version:
                return None
            self._items.move_to_end(mid)
            return item[1]

    def put(self, mid: str, version: str, bank: TemplateBank) -> None:
        size = bank_nbytes(bank)
        with self._lock:
            self._items.pop(mid, None)
            if size > self.max_bytes:
                return
            self._items[mid] = (version, bank, size)
            while sum(s for _, _, s in self._items.values()) > self.max_bytes:
                self._items.popitem(last=False)

    def drop(self, mid: str) -> None:
        with self._lock:
            self._items.pop(mid, None)


class Store:
    """The interface of both backends (see the module docstring). ``open_store(location)`` opens one."""

    location: str
    kind: str  # "disk" or "redis": what /health reports

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def ping(self) -> str | None:
        """None when the store answers; else one sentence saying what is wrong and how to fix it."""
        return None

    def volume_bytes(self) -> int:
        raise NotImplementedError

    # records
    def create(self, record: dict[str, Any], mesh: bytes) -> bool:
        raise NotImplementedError

    def get(self, mid: str) -> dict[str, Any] | None:
        raise NotImplementedError

    def update(self, mid: str, **fields: Any) -> dict[str, Any] | None:
        raise NotImplementedError

    def update_if(self, mid: str, statuses: tuple[str, ...], **fields: Any) -> dict[str, Any] | None:
        raise NotImplementedError

    def ids(self) -> Iterator[str]:
        raise NotImplementedError

    def records(self) -> list[dict[str, Any]]:
        recs = [r for r in (self.get(mid) for mid in self.ids()) if r is not None]
        return sorted(recs, key=lambda r: (r.get("created_at", ""), r["id"]))

    def unfinished(self) -> list[str]:
        return [r["id"] for r in self.records() if r.get("status") in ("queued", "building")]

    def delete(self, mid: str) -> bool:
        raise NotImplementedError

    # payloads
    def mesh(self, mid: str) -> bytes | None:
        raise NotImplementedError

    def put_bank(self, mid: str, bank: TemplateBank) -> None:
        raise NotImplementedError

    def bank(self, mid: str) -> TemplateBank | None:
        raise NotImplementedError

    def ready_bank(self, record: dict[str, Any]) -> TemplateBank:
        """The template bank of the model ``record``; 409 with the reason when its build failed, 409
        (not ready, with its progress) while it is still queued or building."""
        mid, status = record["id"], record["status"]
        if status == "failed":
            reason = clause(record.get("error") or "unknown reason")
            raise BuildFailedError(f"Model '{mid}' failed to build: {reason}; fix the mesh or the template "
                                   "options and upload it again")
        bank = self.bank(mid) if status == "ready" else None
        if bank is None:
            done = 100 * float(record.get("progress") or 0.0)
            raise NotReadyError(f"Model '{mid}' is not ready yet (template build {status}, {done:.0f}% "
                                f"done); retry after Retry-After seconds or poll GET /models/{mid} until it "
                                "is ready")
        return bank

    # builds
    def count_build(self, mid: str) -> int:
        raise NotImplementedError

    def build_count(self, mid: str) -> int:
        raise NotImplementedError

    def try_lock(self, mid: str, lease_s: float) -> str | None:
        """Take the build lease of ``mid`` for ``lease_s`` seconds: a token, or None if another holds it.

        A lease (not a plain lock) so a process that dies mid-build cannot block the model forever:
        the holder renews it while it works (``renew``); once it stops, the lease expires and the
        next process to ask takes over.
        """
        raise NotImplementedError

    def renew(self, mid: str, token: str, lease_s: float) -> bool:
        raise NotImplementedError

    def unlock(self, mid: str, token: str) -> None:
        raise NotImplementedError

    def lock_holder(self, mid: str) -> str | None:
        raise NotImplementedError

    # grasps and cameras (service.cell)
    def put_grasps(self, mid: str, grasps: list[dict[str, Any]]) -> None:
        raise NotImplementedError

    def grasps(self, mid: str) -> list[dict[str, Any]]:
        raise NotImplementedError

    def put_camera(self, name: str, camera: dict[str, Any]) -> bool:
        """Register or replace camera ``name``: True if it is new."""
        raise NotImplementedError

    def camera(self, name: str) -> dict[str, Any] | None:
        raise NotImplementedError

    def cameras(self) -> list[tuple[str, dict[str, Any]]]:
        """Every registered camera as (name, record), by name."""
        raise NotImplementedError

    def delete_camera(self, name: str) -> bool:
        raise NotImplementedError

    # reference photos (service.references)
    def add_reference(self, mid: str, reference: dict[str, Any], limit: int) -> dict[str, Any] | None:
        """Append a reference photo (a dict: ``image`` bytes, ``camera``, ``T_cam_obj``, ``width``,
        ``height``, ...) to the model's, in one transaction with the record's ``references`` count and a
        new ``references_version``: the updated record; None if the model is gone; 409
        (``references_full``) if it has ``limit`` photos already."""
        raise NotImplementedError

    def references(self, mid: str, *, images: bool = False) -> list[dict[str, Any]]:
        """The model's reference photos in the order they were added (each without ``image`` unless
        ``images``); one consistent set even while another process adds or clears them."""
        raise NotImplementedError

    def clear_references(self, mid: str) -> dict[str, Any] | None:
        """Remove every reference photo of the model: the updated record (``references`` 0, a new
        ``references_version``); None if the model is gone."""
        raise NotImplementedError


def references_full(mid: str, n: int, limit: int) -> ConflictError:
    """The 409 of a model that has ``limit`` reference photos already."""
    return ConflictError(f"Model '{mid}' already has {n} reference photos, the most it keeps ({limit}); "
                         f"DELETE /models/{mid}/references first, then post again the few views that cover "
                         "the part's sides")


def new_version() -> str:
    return uuid.uuid4().hex


def new_token() -> str:
    return f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex}"
