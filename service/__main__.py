"""Command line: ``python -m service serve | build | estimate`` (``--help`` on each).

``build`` and ``estimate`` use the same template cache (``POSE_CACHE_DIR``, default
``templates_cache/``) and the same code paths as the HTTP API, and print the same JSON.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from pathlib import Path

from service.errors import ServiceError


def _settings(args: argparse.Namespace):
    from service.settings import Settings

    overrides = {"cache_dir": args.cache_dir} if getattr(args, "cache_dir", None) else {}
    return Settings(**overrides)


def _ensure_built(args: argparse.Namespace, settings, store) -> dict:
    """Register the mesh (idempotent) and build its templates here and now unless they are ready."""
    from service.api.deps import parse_json_object
    from service.builder import register_upload, run_build

    mesh = Path(args.mesh)
    templates = parse_json_object(args.templates, "templates")
    record, _ = register_upload(store, settings, mesh.read_bytes(), filename=mesh.name, name=args.name,
                                units=args.units, symmetry=args.symmetry, templates=templates)
    if record["status"] != "ready":
        run_build(str(settings.cache_dir), record["id"], settings.build_lease_s)
    return store.get(record["id"]) or record


METRICS_DIR_ENV = "PROMETHEUS_MULTIPROC_DIR"  # read by prometheus_client when it is imported


METRICS_DIR_PREFIX = "posecell-metrics-"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process: alive
        return True
    return True


def remove_stale_metrics_dirs(tmp: Path | None = None) -> list[Path]:
    """Delete the private metrics directories of servers that died without removing them (kill -9).

    Each is named ``posecell-metrics-<pid>-<random>``; one whose pid no longer runs is stale."""
    removed = []
    for path in Path(tmp or tempfile.gettempdir()).glob(f"{METRICS_DIR_PREFIX}*"):
        pid = path.name[len(METRICS_DIR_PREFIX):].split("-", 1)[0]
        if path.is_dir() and pid.isdigit() and not _pid_alive(int(pid)):
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    return removed


def prepare_metrics_dir() -> tuple[Path, bool]:
    """An empty directory in ``$PROMETHEUS_MULTIPROC_DIR`` for the workers' metric files: (it, made here).

    Must run before any process of this server imports prometheus_client (the workers inherit the
    variable). Files of an earlier run would add its counts to this one's, so a directory the
    operator named is emptied; otherwise a new private one is made (and removed at exit), and the
    private ones that killed servers left behind are removed first.
    """
    named = os.environ.get(METRICS_DIR_ENV)
    if named:
        path = Path(named)
        path.mkdir(parents=True, exist_ok=True)
        for old in path.glob("*.db"):
            old.unlink()
        return path, False
    remove_stale_metrics_dirs()
    path = Path(tempfile.mkdtemp(prefix=f"{METRICS_DIR_PREFIX}{os.getpid()}-"))
    os.environ[METRICS_DIR_ENV] = str(path)
    return path, True


def _stopped(signum: int, frame: object) -> None:
    raise SystemExit(0)


def cmd_serve(args: argparse.Namespace) -> int:
    import signal

    import uvicorn

    from service.logs import logging_config

    if args.cache_dir:  # uvicorn's worker processes read their Settings from the environment
        os.environ["POSE_CACHE_DIR"] = str(args.cache_dir)
    s = _settings(args)
    metrics_dir, made_here = prepare_metrics_dir()
    # SIGTERM (docker stop): uvicorn stops accepting, answers the requests in flight, runs the
    # lifespan's shutdown (running builds go back to "queued") and then raises the SIGTERM again
    # for whoever handled it before; this handler makes that a clean exit (status 0, the metrics
    # directory removed) instead of death by signal.
    signal.signal(signal.SIGTERM, _stopped)
    try:
        uvicorn.run("service.main:create_app", factory=True, host=args.host or s.host,
                    port=args.port or s.port, workers=args.workers or s.workers, log_level=s.log_level,
                    log_config=logging_config(s.log_level), access_log=False)
    finally:
        if made_here:
            shutil.rmtree(metrics_dir, ignore_errors=True)
    return 0


def cmd_build(args: argparse.Namespace) -> int:
    from service.schemas import ModelInfo
    from service.store import Store

    settings = _settings(args)
    with Store(settings.cache_dir) as store:
        record = _ensure_built(args, settings, store)
    print(ModelInfo.from_record(record).model_dump_json(indent=2))
    return 0 if record["status"] == "ready" else 1


def cmd_estimate(args: argparse.Namespace) -> int:
    from service.api.deps import Loaded, get_ready_model, parse_json_part
    from service.api.estimate import run_estimate
    from service.schemas import Camera, Options
    from service.store import Store

    settings = _settings(args)
    camera_text = Path(args.camera).read_text() if Path(args.camera).is_file() else args.camera
    cam = parse_json_part(camera_text, Camera, "camera")
    opts = parse_json_part(args.options, Options, "options")
    with Store(settings.cache_dir) as store:
        record = _ensure_built(args, settings, store)
        model: Loaded = get_ready_model(record, store)  # 409 with the reason if the build failed
        result = run_estimate(model, Path(args.image).read_bytes(), cam, opts, settings)
    print(result.model_dump_json(indent=2))
    return 0


def _mesh_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("mesh", help="STL, OBJ, PLY, OFF or GLB file")
    p.add_argument("--units", default="mm", choices=["mm", "cm", "m", "in"], help="the mesh's unit")
    p.add_argument("--symmetry", default="auto", choices=["auto", "none", "x", "y", "z"])
    p.add_argument("--templates", default=None, help="JSON object of template-grid options")
    p.add_argument("--name", default=None, help="a label (default: the file name)")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m service", description="posecell: 6D pose service")
    parser.add_argument("--cache-dir", default=None, help="template cache (default: $POSE_CACHE_DIR or "
                        "templates_cache)")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("serve", help="run the HTTP API with uvicorn (host/port/workers from POSE_* settings)")
    p.add_argument("--host", default=None)
    p.add_argument("--port", type=int, default=None)
    p.add_argument("--workers", type=int, default=None)
    p.set_defaults(func=cmd_serve)

    p = sub.add_parser("build", help="build a mesh's templates in this process; print its ModelInfo JSON")
    _mesh_args(p)
    p.set_defaults(func=cmd_build)

    p = sub.add_parser("estimate", help="estimate a pose; print the API's EstimateResult JSON")
    _mesh_args(p)
    p.add_argument("image", help="PNG, JPEG, BMP or TIFF image")
    p.add_argument("--camera", required=True, help='intrinsics JSON file or text: {"fx","fy","cx","cy"}')
    p.add_argument("--options", default=None, help='JSON text, e.g. {"distance_mm": 500}')
    p.set_defaults(func=cmd_estimate)

    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except ServiceError as e:
        print(f"error ({e.status_code}): {e.detail}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
