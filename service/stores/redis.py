"""``RedisStore``: the store on a Redis server shared by API replicas and build workers.

``POSE_STORE=redis://host:6379/0``. Every key starts with ``posecell:v1:`` (``PREFIX``; a change of
layout gets a new version rather than reading the old one wrongly). For a model id ``<id>``::

    posecell:v1:models                 set of every model id
    posecell:v1:model:<id>             JSON record (updated in WATCH/MULTI transactions)
    posecell:v1:mesh:<id>              the uploaded mesh bytes
    posecell:v1:bank:<id>              the current bank version (hex); absent: no bank
    posecell:v1:bank:<id>:<version>    list of the bank's ``np.savez`` bytes in chunks of CHUNK_BYTES
    posecell:v1:lock:<id>              build lease token, with a PX expiry (SET NX PX; renewed by the holder)
    posecell:v1:builds:<id>            INCR counter of build starts
    posecell:v1:grasps:<id>            JSON list of grasps
    posecell:v1:refs:<id>              list of the reference photos' JSON descriptions (camera, T_cam_obj,
                                       size), in the order they were added
    posecell:v1:refimg:<id>            list of their image bytes, as uploaded (same order; both lists
                                       and the record's count and version change in one MULTI)
    posecell:v1:cameras                set of camera names
    posecell:v1:camera:<name>          JSON camera

A bank is written under a new version and then made current, so a reader never sees half a bank, and
every replica's in-process ``BankCache`` (keyed by version) drops a rebuilt or deleted bank at its next
read. A Redis that cannot be reached raises ``StoreUnavailableError`` (503), never a 500.
"""

from __future__ import annotations

import functools
import json
import uuid
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import redis

from service.errors import StoreUnavailableError
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

PREFIX = "posecell:v1:"
CHUNK_BYTES = 4 << 20  # a bank is stored as a list of 4 MiB strings (Redis strings cap at 512 MB)
SOCKET_TIMEOUT_S = 5.0
CONNECT_TIMEOUT_S = 2.0  # a Redis that does not answer: /health says so before a 4 s health check gives up
BANK_VERSION_TTL_S = 60  # an old bank version lingers this long for readers that fetched its version

F = TypeVar("F", bound=Callable[..., Any])

_RENEW = """
if redis.call('GET', KEYS[1]) == ARGV[1] then
  redis.call('PEXPIRE', KEYS[1], ARGV[2]) return 1
end
return 0"""
_UNLOCK = """
if redis.call('GET', KEYS[1]) == ARGV[1] then return redis.call('DEL', KEYS[1]) end
return 0"""


def redact(url: str) -> str:
    """The URL without its password, for sentences and logs."""
    head, sep, tail = url.rpartition("@")
    if not sep:
        return url
    scheme, _, _ = head.partition("://")
    return f"{scheme}://***@{tail}"


def unavailable_sentence(url: str, e: BaseException | None = None) -> str:
    why = f" ({type(e).__name__})" if e is not None else ""
    return (f"The store at {redact(url)} cannot be reached{why}; start Redis or fix POSE_STORE, "
            "and retry")


def _reachable(method: F) -> F:
    @functools.wraps(method)
    def wrapper(self: RedisStore, *args: Any, **kwargs: Any) -> Any:
        try:
            return method(self, *args, **kwargs)
        except (redis.ConnectionError, redis.TimeoutError) as e:
            raise StoreUnavailableError(unavailable_sentence(self.location, e)) from e
    return wrapper  # type: ignore[return-value]


def _k(*parts: str) -> str:
    return PREFIX + ":".join(parts)


class RedisStore(Store):
    kind = "redis"

    def __init__(self, url: str, *, bank_cache_mb: float = DEFAULT_BANK_CACHE_MB) -> None:
        self.location = str(url)
        self.r = redis.Redis.from_url(self.location, socket_timeout=SOCKET_TIMEOUT_S,
                                      socket_connect_timeout=CONNECT_TIMEOUT_S, health_check_interval=10)
        self._banks = BankCache(bank_cache_mb)
        self._renew = self.r.register_script(_RENEW)
        self._unlock = self.r.register_script(_UNLOCK)

    def close(self) -> None:
        self.r.close()

    def ping(self) -> str | None:
        try:
            self.r.ping()
        except (redis.ConnectionError, redis.TimeoutError) as e:
            return unavailable_sentence(self.location, e)
        return None

    @_reachable
    def volume_bytes(self) -> int:
        return int(self.r.info("memory").get("used_memory", 0))

    # --- records ---------------------------------------------------------------------------------

    @_reachable
    def create(self, record: dict[str, Any], mesh: bytes) -> bool:
        mid = record["id"]
        if self.r.exists(_k("model", mid)):
            return False
        self.r.set(_k("mesh", mid), mesh)
        if not self.r.set(_k("model", mid), json.dumps(record), nx=True):
            return False
        self.r.sadd(_k("models"), mid)
        return True

    @_reachable
    def get(self, mid: str) -> dict[str, Any] | None:
        raw = self.r.get(_k("model", mid))
        return None if raw is None else json.loads(raw)

    def _merge(self, mid: str, statuses: tuple[str, ...] | None,
               fields: dict[str, Any]) -> dict[str, Any] | None:
        key = _k("model", mid)
        out: list[dict[str, Any] | None] = [None]

        def tx(pipe: redis.client.Pipeline) -> None:
            raw = pipe.get(key)
            rec = None if raw is None else json.loads(raw)
            if rec is None or (statuses is not None and rec.get("status") not in statuses):
                out[0] = None
                pipe.multi()
                return
            rec.update(fields)
            out[0] = rec
            pipe.multi()
            pipe.set(key, json.dumps(rec), xx=True)

        self.r.transaction(tx, key)
        return out[0]

    @_reachable
    def update(self, mid: str, **fields: Any) -> dict[str, Any] | None:
        """Atomically merge ``fields`` into the record (a WATCH/MULTI transaction); None if it is gone."""
        return self._merge(mid, None, fields)

    @_reachable
    def update_if(self, mid: str, statuses: tuple[str, ...], **fields: Any) -> dict[str, Any] | None:
        return self._merge(mid, statuses, fields)

    @_reachable
    def ids(self) -> Iterator[str]:
        return iter(sorted(m.decode() for m in self.r.smembers(_k("models"))))

    @_reachable
    def delete(self, mid: str) -> bool:
        version = self.r.get(_k("bank", mid))
        kinds = ("model", "mesh", "bank", "builds", "grasps", "lock", "refs", "refimg")
        keys = [_k(kind, mid) for kind in kinds]
        if version is not None:
            keys.append(_k("bank", mid, version.decode()))
        pipe = self.r.pipeline()
        pipe.delete(_k("model", mid))
        pipe.delete(*keys)
        pipe.srem(_k("models"), mid)
        existed = pipe.execute()[0]
        self._banks.drop(mid)
        return bool(existed)

    # --- payloads --------------------------------------------------------------------------------

    @_reachable
    def mesh(self, mid: str) -> bytes | None:
        return self.r.get(_k("mesh", mid))

    @_reachable
    def put_bank(self, mid: str, bank: TemplateBank) -> None:
        data = bank_to_bytes(bank)
        version = uuid.uuid4().hex
        chunks = [data[i:i + CHUNK_BYTES] for i in range(0, len(data), CHUNK_BYTES)] or [b""]
        key = _k("bank", mid, version)
        pipe = self.r.pipeline()
        pipe.delete(key)
        for c in chunks:
            pipe.rpush(key, c)
        pipe.execute()
        old = self.r.getset(_k("bank", mid), version)
        if old is not None:  # readers that just fetched the old version still find its data briefly
            self.r.expire(_k("bank", mid, old.decode()), BANK_VERSION_TTL_S)

    @_reachable
    def bank(self, mid: str) -> TemplateBank | None:
        """The bank: from this process's ``BankCache`` while its version is current, else from Redis."""
        raw = self.r.get(_k("bank", mid))
        if raw is None:
            return None
        version = raw.decode()
        bank = self._banks.get(mid, version)
        if bank is not None:
            return bank
        chunks = self.r.lrange(_k("bank", mid, version), 0, -1)
        if not chunks:
            return None
        bank = bank_from_bytes(b"".join(chunks))
        self._banks.put(mid, version, bank)
        return bank

    # --- builds ----------------------------------------------------------------------------------

    @_reachable
    def count_build(self, mid: str) -> int:
        return int(self.r.incr(_k("builds", mid)))

    @_reachable
    def build_count(self, mid: str) -> int:
        return int(self.r.get(_k("builds", mid)) or 0)

    @_reachable
    def try_lock(self, mid: str, lease_s: float) -> str | None:
        token = new_token()
        ok = self.r.set(_k("lock", mid), token, nx=True, px=max(1, int(lease_s * 1000)))
        return token if ok else None

    @_reachable
    def renew(self, mid: str, token: str, lease_s: float) -> bool:
        return bool(self._renew(keys=[_k("lock", mid)], args=[token, max(1, int(lease_s * 1000))]))

    @_reachable
    def unlock(self, mid: str, token: str) -> None:
        self._unlock(keys=[_k("lock", mid)], args=[token])

    @_reachable
    def lock_holder(self, mid: str) -> str | None:
        raw = self.r.get(_k("lock", mid))
        return None if raw is None else raw.decode()

    # --- grasps and cameras ----------------------------------------------------------------------

    @_reachable
    def put_grasps(self, mid: str, grasps: list[dict[str, Any]]) -> None:
        self.r.set(_k("grasps", mid), json.dumps(list(grasps)))

    @_reachable
    def grasps(self, mid: str) -> list[dict[str, Any]]:
        raw = self.r.get(_k("grasps", mid))
        return [] if raw is None else list(json.loads(raw))

    @_reachable
    def put_camera(self, name: str, camera: dict[str, Any]) -> bool:
        pipe = self.r.pipeline()
        pipe.set(_k("camera", name), json.dumps(camera))
        pipe.sadd(_k("cameras"), name)
        return bool(pipe.execute()[1])

    @_reachable
    def camera(self, name: str) -> dict[str, Any] | None:
        raw = self.r.get(_k("camera", name))
        return None if raw is None else json.loads(raw)

    @_reachable
    def cameras(self) -> list[tuple[str, dict[str, Any]]]:
        names = sorted(n.decode() for n in self.r.smembers(_k("cameras")))
        return [(n, c) for n, c in ((n, self.camera(n)) for n in names) if c is not None]

    @_reachable
    def delete_camera(self, name: str) -> bool:
        pipe = self.r.pipeline()
        pipe.delete(_k("camera", name))
        pipe.srem(_k("cameras"), name)
        return bool(pipe.execute()[0])

    # --- reference photos (service.references) -------------------------------------------------------

    @_reachable
    def add_reference(self, mid: str, reference: dict[str, Any], limit: int) -> dict[str, Any] | None:
        described = json.dumps({k: v for k, v in reference.items() if k != "image"})
        model, refs = _k("model", mid), _k("refs", mid)
        out: list[Any] = [None, 0]  # the updated record, the count when full

        def tx(pipe: redis.client.Pipeline) -> None:
            raw, n = pipe.get(model), int(pipe.llen(refs))
            out[0], out[1] = None, 0
            pipe.multi()
            if raw is None:
                return
            if n >= limit:
                out[1] = n
                return
            rec = json.loads(raw)
            rec.update(references=n + 1, references_version=new_version())
            out[0] = rec
            pipe.rpush(refs, described)
            pipe.rpush(_k("refimg", mid), bytes(reference["image"]))
            pipe.set(model, json.dumps(rec), xx=True)

        self.r.transaction(tx, model, refs)
        if out[1]:
            raise references_full(mid, out[1], limit)
        return out[0]

    @_reachable
    def references(self, mid: str, *, images: bool = False) -> list[dict[str, Any]]:
        if not images:
            return [json.loads(d) for d in self.r.lrange(_k("refs", mid), 0, -1)]
        pipe = self.r.pipeline(transaction=True)  # both lists as one MULTI saw them
        pipe.lrange(_k("refs", mid), 0, -1)
        pipe.lrange(_k("refimg", mid), 0, -1)
        described, imgs = pipe.execute()
        out = [json.loads(d) for d in described]
        for item, data in zip(out, imgs, strict=True):
            item["image"] = data
        return out

    @_reachable
    def clear_references(self, mid: str) -> dict[str, Any] | None:
        model = _k("model", mid)
        out: list[dict[str, Any] | None] = [None]

        def tx(pipe: redis.client.Pipeline) -> None:
            raw = pipe.get(model)
            pipe.multi()
            pipe.delete(_k("refs", mid), _k("refimg", mid))
            out[0] = None
            if raw is not None:
                rec = json.loads(raw)
                rec.update(references=0, references_version=new_version())
                out[0] = rec
                pipe.set(model, json.dumps(rec), xx=True)

        self.r.transaction(tx, model)
        return out[0]
