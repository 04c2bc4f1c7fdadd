"""The template cache: model records, uploaded meshes, template banks, build status and build locks.

The ONLY module that imports diskcache. One ``Store`` per process opens the cache directory;
several processes (uvicorn workers, build processes) share it safely (SQLite underneath).

Keys, for a model id ``<id>``::

    model:<id>    record (dict): name, units, options, status, progress, error, extents, ...
    mesh:<id>     the uploaded mesh bytes, exactly as sent
    bank:<id>     the template bank, ``np.savez`` of ``TemplateBank.to_arrays()``
    lock:<id>     build lease: the token of the process building <id>; expires unless renewed
    builds:<id>   how many times a build of <id> has started (a crash-resumed build counts twice)
    grasps:<id>   the model's grasps (list of dicts, as PUT /models/{id}/grasps sent them)
    camera:<name> a registered camera (dict: intrinsics, image size, extrinsics, plane)

Ids are content hashes (``model_id``): the same mesh bytes with the same options give the same id.
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
from pathlib import Path
from typing import Any

import diskcache
import numpy as np

from service.errors import BuildFailedError, NotReadyError, clause
from service.vision.bank import TemplateBank

ID_HEX_CHARS = 20
BANK_LRU_SIZE = 8  # banks kept loaded per process


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


class Store:
    def __init__(self, directory: str | os.PathLike[str]) -> None:
        self.directory = Path(directory)
        self._cache = diskcache.Cache(str(self.directory))
        self._banks: OrderedDict[str, TemplateBank] = OrderedDict()
        self._banks_lock = threading.Lock()

    def close(self) -> None:
        self._cache.close()

    def volume_bytes(self) -> int:
        """Size of the cache on disk, bytes: its SQLite database and the value files beside it."""
        return int(self._cache.volume())

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- records --------------------------------------------------------------------------------

    def create(self, record: dict[str, Any], mesh: bytes) -> bool:
        """Store a new model (mesh first, then its record). False if the id already exists."""
        mid = record["id"]
        if f"model:{mid}" in self._cache:
            return False
        self._cache.set(f"mesh:{mid}", mesh)
        return bool(self._cache.add(f"model:{mid}", dict(record)))

    def get(self, mid: str) -> dict[str, Any] | None:
        return self._cache.get(f"model:{mid}")

    def update(self, mid: str, **fields: Any) -> dict[str, Any] | None:
        """Atomically merge ``fields`` into the record (across processes); None if it is gone."""
        with self._cache.transact():
            rec = self._cache.get(f"model:{mid}")
            if rec is None:
                return None
            rec.update(fields)
            self._cache.set(f"model:{mid}", rec)
        return rec

    def update_if(self, mid: str, statuses: tuple[str, ...], **fields: Any) -> dict[str, Any] | None:
        """``update`` only while the record's status is one of ``statuses``; None if it is not (or gone).

        A build being stopped puts its model back to "queued" this way, so it can never undo a
        "ready" or "failed" that was written a moment before."""
        with self._cache.transact():
            rec = self._cache.get(f"model:{mid}")
            if rec is None or rec.get("status") not in statuses:
                return None
            rec.update(fields)
            self._cache.set(f"model:{mid}", rec)
        return rec

    def ids(self) -> Iterator[str]:
        for key in self._cache.iterkeys():
            if isinstance(key, str) and key.startswith("model:"):
                yield key[len("model:"):]

    def records(self) -> list[dict[str, Any]]:
        recs = [r for r in (self.get(mid) for mid in self.ids()) if r is not None]
        return sorted(recs, key=lambda r: (r.get("created_at", ""), r["id"]))

    def unfinished(self) -> list[str]:
        return [r["id"] for r in self.records() if r.get("status") in ("queued", "building")]

    def delete(self, mid: str) -> bool:
        """Remove every record of the model. False if it did not exist."""
        existed = self._cache.delete(f"model:{mid}")
        for kind in ("mesh", "bank", "builds", "grasps", "lock"):
            self._cache.delete(f"{kind}:{mid}")
        with self._banks_lock:
            self._banks.pop(mid, None)
        return bool(existed)

    # --- payloads -------------------------------------------------------------------------------

    def mesh(self, mid: str) -> bytes | None:
        return self._cache.get(f"mesh:{mid}")

    def put_bank(self, mid: str, bank: TemplateBank) -> None:
        self._cache.set(f"bank:{mid}", bank_to_bytes(bank))

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

    def bank(self, mid: str) -> TemplateBank | None:
        """The model's template bank, from the in-process LRU or the cache; None if not built."""
        with self._banks_lock:
            if mid in self._banks:
                self._banks.move_to_end(mid)
                return self._banks[mid]
        data = self._cache.get(f"bank:{mid}")
        if data is None:
            return None
        bank = bank_from_bytes(data)
        with self._banks_lock:
            self._banks[mid] = bank
            self._banks.move_to_end(mid)
            while len(self._banks) > BANK_LRU_SIZE:
                self._banks.popitem(last=False)
        return bank

    # --- builds ---------------------------------------------------------------------------------

    def count_build(self, mid: str) -> int:
        return int(self._cache.incr(f"builds:{mid}"))

    def build_count(self, mid: str) -> int:
        return int(self._cache.get(f"builds:{mid}", 0))

    def try_lock(self, mid: str, lease_s: float) -> str | None:
        """Take the build lease of ``mid`` for ``lease_s`` seconds: a token, or None if another holds it.

        A lease (not a plain lock) so a process that dies mid-build cannot block the model forever:
        the holder renews it while it works (``renew``); once it stops, the lease expires and the
        next process to ask takes over.
        """
        token = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex}"
        return token if self._cache.add(f"lock:{mid}", token, expire=lease_s) else None

    def renew(self, mid: str, token: str, lease_s: float) -> bool:
        with self._cache.transact():
            if self._cache.get(f"lock:{mid}") != token:
                return False
            self._cache.set(f"lock:{mid}", token, expire=lease_s)
        return True

    def unlock(self, mid: str, token: str) -> None:
        with self._cache.transact():
            if self._cache.get(f"lock:{mid}") == token:
                self._cache.delete(f"lock:{mid}")

    def lock_holder(self, mid: str) -> str | None:
        return self._cache.get(f"lock:{mid}")

    # --- grasps and cameras (service.cell) --------------------------------------------------------

    def put_grasps(self, mid: str, grasps: list[dict[str, Any]]) -> None:
        self._cache.set(f"grasps:{mid}", list(grasps))

    def grasps(self, mid: str) -> list[dict[str, Any]]:
        return list(self._cache.get(f"grasps:{mid}", []))

    def put_camera(self, name: str, camera: dict[str, Any]) -> bool:
        """Register or replace camera ``name``: True if it is new."""
        with self._cache.transact():
            created = f"camera:{name}" not in self._cache
            self._cache.set(f"camera:{name}", dict(camera))
        return created

    def camera(self, name: str) -> dict[str, Any] | None:
        return self._cache.get(f"camera:{name}")

    def cameras(self) -> list[tuple[str, dict[str, Any]]]:
        """Every registered camera as (name, record), by name."""
        names = sorted(k[len("camera:"):] for k in self._cache.iterkeys()
                       if isinstance(k, str) and k.startswith("camera:"))
        return [(n, c) for n, c in ((n, self.camera(n)) for n in names) if c is not None]

    def delete_camera(self, name: str) -> bool:
        return bool(self._cache.delete(f"camera:{name}"))
