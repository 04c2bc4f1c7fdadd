"""Template builds: registering an upload, and building its template bank off the event loop.

An upload is decoded once (bad files fail at once with 415/422), registered under its content id
with status ``queued``, and handed to the ``Builder`` (``local.py``) owned by the app's lifespan. A mesh
file over ``IN_PROCESS_MESH_BYTES`` is decoded in a process of its own (``check_mesh``): decoding a 100 MB
STL peaks at ~1.4 GB, and a server process that did it itself kept most of that after the model
was deleted (its heap keeps freed memory mapped for the estimates, ``vision.memory``). The Builder runs
each build in a process of its own (``python -c`` ``worker_main``, at most ``build_workers`` at a time),
so that it can end exactly that build: a DELETE kills it at once, a stop sends it SIGTERM.
``run_build`` opens its own ``Store`` on the shared cache dir and takes the model's build lease, so
across all service processes a model is built once::

    queued -> building -> ready | failed

Progress (0..1) is written to the record every ``PROGRESS_STEP``. A build that was interrupted
(process stopped or killed) stays ``queued``/``building``; at start-up every service process
re-queues those, the first to get the lease builds and the others wait for it to finish. A lease
whose process died expires after ``Settings.build_lease_s``, and the build is taken over.

Bounded: a mesh over ``decode.TEMPLATE_FACE_BUDGET`` faces is simplified to it before the build, and
the build process's address space is capped at ``Settings.build_memory_mb`` (a build that needs more
fails with a sentence instead of taking the host). Every ``WATCH_S`` the build's watch thread checks
that its model still exists (a DELETE from any process ends it) and that the service that started it
is alive (a worker whose server was killed puts its model back to ``queued`` and exits: no orphans).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from service.decode import MeshFacts, decode_mesh, fit_face_budget, inspect_mesh
from service.errors import (
    ServiceError,
    TooLargeError,
    UnprocessableError,
    UnsupportedMediaError,
    clause,
    sentence,
)
from service.logs import configure_like
from service.settings import Settings
from service.stores import open_store
from service.stores.base import Store, model_id
from service.vision.bank import TemplateBank

log = logging.getLogger("service")

PROGRESS_STEP = 0.02  # write progress at most every 2 %
LEASE_POLL_S = 0.5  # how often a process waiting for another's build looks again
SHUTDOWN_GRACE_S = 5.0  # a stopping service waits this long for a build process to put its model back
MAX_BUILD_DEATHS = 3  # a build whose process keeps dying (OOM) is marked failed after this many
WATCH_S = 0.2  # how often a build checks that its model still exists and its service is alive
EXIT_STOPPED = 128 + signal.SIGTERM  # a build process that put its model back to "queued" on request
ACTIVE = ("queued", "building")  # what a stopping build may put back to "queued" (never "ready"/"failed")
# Mesh files up to this size are decoded in the server process (peak ~14x the file: ~60 MB, which
# its heap may keep); larger ones in a process of their own, which pays ~2 s of imports and frees
# all it used when it exits.
IN_PROCESS_MESH_BYTES = 4 << 20
_MESH_CHECKS = threading.BoundedSemaphore(1)  # one mesh-checking process at a time per server process
_ERRORS: dict[int, type[ServiceError]] = {
    e.status_code: e for e in (TooLargeError, UnsupportedMediaError, UnprocessableError)}


def register_upload(store: Store, settings: Settings, data: bytes, *, filename: str, name: str | None = None,
                    units: str = "mm", symmetry: str = "auto",
                    templates: dict[str, Any] | None = None) -> tuple[dict[str, Any], bool]:
    """Validate and store an uploaded mesh: ``(record, needs_build)``.

    Idempotent: the same bytes with the same options give the same id and the existing record
    (a failed model is queued again: uploading it again is how a client retries). ``templates``
    overrides ``settings.template_grid`` key by key; the record keeps exactly what was asked for
    (the vision code tells an explicit option from a default).
    """
    from service.vision.model.grid import merge_grid

    grid = {**settings.template_grid, **(templates or {})}
    try:  # bad options fail the upload now (422), not the build later
        merge_grid(grid)
    except ValueError as e:
        raise UnprocessableError(f"The templates options are invalid: {clause(e)}; fix them and upload "
                                 "again") from e
    mid = model_id(data, units=units, symmetry=symmetry, templates=grid)
    existing = store.get(mid)
    if existing is None:
        facts = check_mesh(data, filename, units, memory_mb=settings.build_memory_mb)  # 415/422 now
        record = {
            "id": mid, "name": name or filename[:200], "filename": filename, "units": units,
            "symmetry_option": symmetry, "templates": grid,
            "status": "queued", "progress": 0.0, "error": None, "n_templates": None,
            "extents_mm": list(facts.extents_mm),
            # the upload's warnings say when the mesh has holes (ModelInfo.from_record)
            "watertight": facts.watertight, "open_edges": facts.open_edges,
            "nonmanifold_edges": facts.nonmanifold_edges,
            "symmetry": symmetry_of_option(symmetry),
            "created_at": datetime.now(UTC).isoformat(),
        }
        if store.create(record, data):
            return record, True
        existing = store.get(mid)  # another process registered it a moment ago
    if existing is not None and existing["status"] == "failed":
        return store.update(mid, status="queued", progress=0.0, error=None) or existing, True
    return existing or {}, False


def check_mesh(data: bytes, filename: str, units: str = "mm", *, memory_mb: int | None = None,
               in_process_bytes: int = IN_PROCESS_MESH_BYTES) -> MeshFacts:
    """``decode.inspect_mesh`` of an upload (its 415/422 on bad bytes): here for a file of at most
    ``in_process_bytes``, else in a process of its own (capped at ``memory_mb`` MiB of address space),
    so that the server never holds a large decoded mesh and its memory returns once the process exits."""
    if len(data) <= in_process_bytes:
        return inspect_mesh(data, filename, units)
    args = json.dumps({"filename": filename, "units": units, "memory_mb": int(memory_mb or 0)})
    with _MESH_CHECKS:
        proc = subprocess.run([sys.executable, "-c", _CHECK_CODE, args], input=data, capture_output=True,
                              env=child_env())
    try:
        out = json.loads(proc.stdout.decode().strip().splitlines()[-1])
    except (ValueError, IndexError):
        out = None
    if proc.returncode != 0 or not isinstance(out, dict):
        log.error("mesh check process exited with status %s: %s", proc.returncode,
                  proc.stderr.decode(errors="replace")[-2000:])
        raise UnprocessableError(f"Reading the mesh in '{filename[:80]}' failed (its process exited with "
                                 f"status {proc.returncode}: out of memory?); decimate the mesh or try again")
    if "detail" in out:
        raise _ERRORS.get(int(out["status"]), UnprocessableError)(out["detail"])
    ext = [float(x) for x in out["extents_mm"]]
    return MeshFacts((ext[0], ext[1], ext[2]), int(out["open_edges"]), int(out["nonmanifold_edges"]))


def check_main(argv: list[str]) -> int:
    """A mesh-checking process's entry point (``check_mesh``): the file's bytes on stdin, its name,
    unit and memory cap as JSON in ``argv[0]``; one JSON line on stdout: the facts, or the error's
    ``status`` and ``detail``."""
    args = json.loads(argv[0])
    result = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)  # whatever a library prints goes to stderr: stdout carries the one result line
    data = sys.stdin.buffer.read()
    limit_memory(args["memory_mb"])
    try:
        facts = inspect_mesh(data, args["filename"], args["units"])
        out: dict[str, Any] = {"extents_mm": list(facts.extents_mm), "open_edges": facts.open_edges,
                               "nonmanifold_edges": facts.nonmanifold_edges}
    except ServiceError as e:
        out = {"status": e.status_code, "detail": e.detail}
        if isinstance(e.__cause__, MemoryError):  # decode_mesh says "check the file": here it is the cap
            out = {"status": UnprocessableError.status_code, "detail": sentence(
                f"Reading the mesh in '{args['filename'][:80]}' needed more than {args['memory_mb']:,} MB "
                "(POSE_BUILD_MEMORY_MB); decimate the mesh or raise the limit")}
    result.write(json.dumps(out) + "\n")
    result.close()
    return 0


_CHECK_CODE = "import sys; from service.jobs.build import check_main; sys.exit(check_main(sys.argv[1:]))"


def child_env() -> dict[str, str]:
    """The environment of a process this service starts: it imports this very package, wherever it
    was imported from here."""
    import service

    package_root = str(Path(service.__file__).resolve().parents[1])
    paths = [package_root, *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(dict.fromkeys(paths))}


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


def run_build(location: str, mid: str, lease_s: float, *, parent_pid: int | None = None,
              memory_mb: int | None = None) -> str:
    """Build model ``mid``'s template bank (in a build process, or in-process for the CLI).

    Returns the final status: "ready", "failed" or "deleted". A SIGTERM while building puts the
    model back to "queued" (it resumes at the next start-up), releases the lease and ends the
    process at once (status 143). That is done by the lease's watch thread, not by unwinding the
    main thread: the main thread may be waiting on a thread pool that would first render every
    remaining view, longer than the stopping service waits before it kills the process, which
    would leave the model "building" until its lease ran out. The same thread ends the process when
    the model is deleted (within ``WATCH_S``) or when ``parent_pid`` is no longer this process's
    parent (the service died). "Back to queued" never overwrites a build that finished meanwhile.
    """
    from service.vision.pipeline import build_templates

    store = open_store(location)
    token: str | None = None
    wake = threading.Event()  # the watch stops: the build ended, or a SIGTERM came
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

        def put_back_and_exit(why: str, token: str) -> None:
            store.update_if(mid, ACTIVE, status="queued")
            store.unlock(mid, token)
            log.info("template build of model %s stopped (%s); it resumes at the next start-up", mid, why)
            os._exit(EXIT_STOPPED)

        def watch(token: str = token) -> None:
            renewed = time.monotonic()
            while not wake.wait(WATCH_S):
                if parent_pid is not None and os.getppid() != parent_pid:
                    put_back_and_exit("its service process is gone", token)
                if store.get(mid) is None:  # deleted, by this service or another: stop, free the memory
                    store.unlock(mid, token)
                    log.info("template build of model %s stopped: the model was deleted", mid)
                    os._exit(0)
                if time.monotonic() - renewed >= lease_s / 3:
                    store.renew(mid, token, lease_s)
                    renewed = time.monotonic()
            if sigterm.is_set():
                put_back_and_exit("SIGTERM", token)

        heartbeat = threading.Thread(target=watch, name=f"lease-{mid}", daemon=True)
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
            mesh = fit_face_budget(mesh)
            bank = build_templates(mesh, symmetry=rec["symmetry_option"], grid=dict(rec["templates"]),
                                   progress=progress)
            check_bank(bank)
        except _DeletedError:
            return "deleted"
        except Exception as e:
            if not _out_of_memory(e):
                log.exception("template build of model %s failed", mid)
                reason = sentence(getattr(e, "detail", None) or clause(e) or type(e).__name__)
                return "failed" if store.update(mid, status="failed", error=reason) is not None else "deleted"
            log.exception("template build of model %s ran out of memory", mid)
            cap = f"its limit of {memory_mb:,} MB (POSE_BUILD_MEMORY_MB)" if memory_mb else "the memory left"
            reason = sentence(f"The template build needed more than {cap}; use a coarser template grid "
                              "(larger tilt_step_deg / view_step_deg, smaller render_px) or raise the limit")
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
            store.update_if(mid, ACTIVE, status="queued")
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


MIN_TEMPLATE_POINTS = 32  # the coarse search's level A samples this many border points per view


def check_bank(bank: TemplateBank) -> None:
    """422 (the build fails with this sentence) for a bank a search cannot use: a view whose border has
    fewer points than the coarse search samples (a part that is a line or a speck from that side; its
    estimates failed with a 500 and line-like views fit any straight edge)."""
    import numpy as np

    counts = np.diff(np.asarray(bank.offsets))
    k = int(np.argmin(counts))
    if counts[k] < MIN_TEMPLATE_POINTS:
        raise UnprocessableError(f"Seen from template view {k} the part's outline has only {int(counts[k])} "
                                 f"border points, fewer than the {MIN_TEMPLATE_POINTS} a search needs (the "
                                 "mesh is a line or a speck from that side); upload the part as a solid with "
                                 "its real thickness, or a larger render_px")


def _out_of_memory(e: BaseException) -> bool:
    """A MemoryError, or OpenCV's way of saying the same (cv2.error "Insufficient memory")."""
    return isinstance(e, MemoryError) or "Insufficient memory" in str(e)


def limit_memory(memory_mb: int | None) -> None:
    """Cap this process's address space at ``memory_mb`` MiB (allocations past it raise MemoryError)."""
    if not memory_mb:
        return
    import resource

    cap = int(memory_mb) << 20
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    resource.setrlimit(resource.RLIMIT_AS, (cap if hard == resource.RLIM_INFINITY else min(cap, hard), hard))


def worker_main(argv: list[str]) -> int:
    """A build process's entry point: ``location mid lease_s parent_pid memory_mb log_level threads``.

    The process logs like its service and keeps to the service's thread budget (``POSE_THREADS``;
    an empty ``threads``: all cores)."""
    from service.vision import threads as thread_budget

    location, mid, lease_s, parent_pid, memory_mb, level, threads = argv
    configure_like(level or None)
    thread_budget.configure(int(threads) if threads else None)
    limit_memory(int(memory_mb))
    status = run_build(location, mid, float(lease_s), parent_pid=int(parent_pid), memory_mb=int(memory_mb))
    log.info("template build of model %s: %s", mid, status)
    return 0


WORKER_CODE = "import sys; from service.jobs.build import worker_main; sys.exit(worker_main(sys.argv[1:]))"
