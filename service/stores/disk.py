"""``DiskStore``: the store in a diskcache directory (the default; see ``service.store``).

The ONLY module that imports diskcache. Several processes on one machine (uvicorn workers, build
processes) share the directory safely (SQLite underneath). Keys are the logical names of
``service.store`` as they are; a model's reference photos are ``refs:<id>`` (the list of their
descriptions, each naming its image) and ``refimg:<id>:<key>`` (each image's bytes), so listing them
reads no image.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import diskcache

from service.stores.base import (
    DEFAULT_BANK_CACHE_MB,
    BankCache,
    Store,
    bank_from_bytes,
    bank_to_bytes,
    new_token,
    new_version,
    references_full,
)
from service.vision.bank import TemplateBank


class DiskStore(Store):
    kind = "disk"

    def __init__(self, directory: str | os.PathLike[str], *,
                 bank_cache_mb: float = DEFAULT_BANK_CACHE_MB) -> None:
        self.directory = Path(directory)
        self.location = str(self.directory)
        self._cache = diskcache.Cache(str(self.directory))
        self._banks = BankCache(bank_cache_mb)

    def close(self) -> None:
        self._cache.close()

    def volume_bytes(self) -> int:
        """Size of the cache on disk, bytes: its SQLite database and the value files beside it."""
        return int(self._cache.volume())

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

    def delete(self, mid: str) -> bool:
        """Remove every record of the model. False if it did not exist."""
        existed = self._cache.delete(f"model:{mid}")
        with self._cache.transact():
            self._delete_reference_images(mid)
        for kind in ("mesh", "bank", "bankver", "builds", "grasps", "lock", "refs"):
            self._cache.delete(f"{kind}:{mid}")
        self._banks.drop(mid)
        return bool(existed)

    # --- payloads -------------------------------------------------------------------------------

    def mesh(self, mid: str) -> bytes | None:
        return self._cache.get(f"mesh:{mid}")

    def put_bank(self, mid: str, bank: TemplateBank) -> None:
        """Store the bank under a new version (``bankver:<id>``): every process's loaded copy is stale."""
        with self._cache.transact():
            self._cache.set(f"bank:{mid}", bank_to_bytes(bank))
            self._cache.set(f"bankver:{mid}", uuid.uuid4().hex)

    def bank(self, mid: str) -> TemplateBank | None:
        """The model's template bank, from this process's ``BankCache`` or the cache; None if not built."""
        # a bank written before banks had versions (an existing cache volume) is version "0"
        version = self._cache.get(f"bankver:{mid}", "0")
        bank = self._banks.get(mid, version)
        if bank is not None:
            return bank
        data = self._cache.get(f"bank:{mid}")
        if data is None:
            return None
        bank = bank_from_bytes(data)
        self._banks.put(mid, version, bank)
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
        token = new_token()
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

    # --- reference photos (service.references) -----------------------------------------------------

    def add_reference(self, mid: str, reference: dict[str, Any], limit: int) -> dict[str, Any] | None:
        key = uuid.uuid4().hex
        described = {k: v for k, v in reference.items() if k != "image"}
        full = 0
        with self._cache.transact():
            rec = self._cache.get(f"model:{mid}")
            if rec is None:
                return None
            refs = list(self._cache.get(f"refs:{mid}", []))
            if len(refs) >= limit:
                full = len(refs)
            else:
                self._cache.set(f"refimg:{mid}:{key}", bytes(reference["image"]))
                refs.append({**described, "image_key": key})
                self._cache.set(f"refs:{mid}", refs)
                rec.update(references=len(refs), references_version=new_version())
                self._cache.set(f"model:{mid}", rec)
        if full:
            raise references_full(mid, full, limit)
        return rec

    def references(self, mid: str, *, images: bool = False) -> list[dict[str, Any]]:
        out = []
        with self._cache.transact():
            for ref in self._cache.get(f"refs:{mid}", []):
                item = {k: v for k, v in ref.items() if k != "image_key"}
                if images:
                    item["image"] = self._cache.get(f"refimg:{mid}:{ref['image_key']}")
                out.append(item)
        return out

    def _delete_reference_images(self, mid: str) -> None:
        """Delete the image bytes of the model's reference photos (inside the caller's transaction)."""
        for ref in self._cache.get(f"refs:{mid}", []):
            self._cache.delete(f"refimg:{mid}:{ref['image_key']}")

    def clear_references(self, mid: str) -> dict[str, Any] | None:
        with self._cache.transact():
            self._delete_reference_images(mid)
            self._cache.delete(f"refs:{mid}")
            rec = self._cache.get(f"model:{mid}")
            if rec is None:
                return None
            rec.update(references=0, references_version=new_version())
            self._cache.set(f"model:{mid}", rec)
        return rec
