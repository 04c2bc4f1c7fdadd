"""Command line: ``python -m service serve | build | estimate | warm-up | worker`` (``--help`` on each).

``build`` and ``estimate`` use the same template cache (``POSE_CACHE_DIR``, default
``templates_cache/``) and the same code paths as the HTTP API, and print the same JSON.
"""

from __future__ import annotations

import argparse
import base64
import os
import shutil
import sys
import tempfile
import threading
from pathlib import Path

from service.errors import ServiceError


def _settings(args: argparse.Namespace):
    from service.settings import Settings
    from service.vision import threads

    overrides = {"cache_dir": args.cache_dir} if getattr(args, "cache_dir", None) else {}
    settings = Settings(**overrides)
    threads.configure(settings.threads)
    return settings


class CliError(Exception):
    """A mistake on the command line (a missing file, ...): printed as one line, exit status 2."""


def _existing(path: str, what: str, hint: str) -> Path:
    p = Path(path)
    if not p.is_file():
        raise CliError(f"{what} file not found: {path} ({'it is a directory; ' if p.is_dir() else ''}{hint})")
    return p


def _progress(location: str, mid: str, done: threading.Event, stream=None) -> None:
    """Until ``done``: one self-overwriting line on ``stream`` (stderr) with the build's progress."""
    from service.stores import open_store

    stream = stream or sys.stderr
    with open_store(location) as store:
        while not done.wait(PROGRESS_EVERY_S):
            rec = store.get(mid) or {}
            stream.write(f"\rbuilding templates of {mid}: {rec.get('status', '?')} "
                         f"{100 * float(rec.get('progress') or 0.0):3.0f}%")
            stream.flush()
    stream.write("\r\033[K")
    stream.flush()


def _ensure_built(args: argparse.Namespace, settings, store) -> dict:
    """Register the mesh (idempotent) and build its templates here and now unless they are ready.
    On a terminal, a progress line on stderr while it builds."""
    from service.form_parts import parse_json_object
    from service.jobs.build import register_upload, run_build

    mesh = _existing(args.mesh, "mesh", "give an STL, OBJ, PLY, OFF or GLB file")
    templates = parse_json_object(args.templates, "templates")
    record, _ = register_upload(store, settings, mesh.read_bytes(), filename=mesh.name, name=args.name,
                                units=args.units, symmetry=args.symmetry, templates=templates)
    for warning in _warnings(record):
        print(f"warning: {warning}", file=sys.stderr)
    if record["status"] != "ready":
        done = threading.Event()
        shown = threading.Thread(target=_progress, args=(settings.store_location, record["id"], done),
                                 daemon=True)
        if sys.stderr.isatty():
            shown.start()
        try:
            run_build(settings.store_location, record["id"], settings.build_lease_s)
        finally:
            done.set()
            if shown.is_alive():
                shown.join()
    return store.get(record["id"]) or record


def _warnings(record: dict) -> list[str]:
    from service.cell import extent_warnings

    return extent_warnings(record.get("extents_mm") or [], record.get("units") or "mm")


PROGRESS_EVERY_S = 0.5  # how often the build's progress line is redrawn on a terminal
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


def cmd_warm_up(args: argparse.Namespace) -> int:
    """Compile (or load) every numba kernel into NUMBA_CACHE_DIR: what a server's start-up warm-up does,
    done ahead (the Docker image runs it when it is built, so a container is ready in seconds)."""
    import time

    from service.vision import pipeline

    _settings(args)
    t0 = time.perf_counter()
    out = pipeline.warm_up()
    print(f"warm-up done in {(time.perf_counter() - t0) * 1000:.0f} ms (synthetic part found: {out.found})")
    return 0 if out.found else 1


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
    """Build the mesh's templates, then calibrate it for a plane (``POSE_PLANE_CALIBRATION_SCENES``), as
    the service does in the background; print its ModelInfo."""
    from service.plane_calibrations import calibrate_plane_stored, plane_calibration_due
    from service.schemas import ModelInfo
    from service.stores import open_store

    settings = _settings(args)
    scenes = settings.plane_calibration_scenes
    with open_store(settings.store_location) as store:
        record = _ensure_built(args, settings, store)
        if plane_calibration_due(record, scenes):
            def told(done: int, total: int) -> None:
                print(f"calibrating for a plane: scene {done + 1} of {total}", file=sys.stderr, flush=True)

            record = calibrate_plane_stored(store, record["id"], store.ready_bank(record), scenes, told) \
                or record
    print(ModelInfo.from_record(record, scenes).model_dump_json(indent=2))
    return 0 if record["status"] == "ready" else 1


def _camera_text(arg: str) -> str:
    """``--camera``: JSON text (starts with ``{``) or the name of a JSON file, which must exist."""
    if arg.lstrip().startswith("{"):
        return arg
    return _existing(arg, "camera", 'give a JSON file such as examples/cam.json, or the JSON itself: '
                     '\'{"fx": 1100, "fy": 1100, "cx": 643, "cy": 477}\'').read_text()


def cmd_estimate(args: argparse.Namespace) -> int:
    from service.cell_io import check_robot_pose, estimate_options, estimate_result, grasps_of, resolve_camera
    from service.form_parts import parse_json_object
    from service.references import appearance_of
    from service.stores import open_store

    settings = _settings(args)
    camera_text = _camera_text(args.camera)
    parse_json_object(camera_text, "camera")  # bad JSON fails before any file is read
    parse_json_object(args.options, "options")
    image = _existing(args.image, "image", "give a PNG, JPEG, BMP or TIFF file")
    with open_store(settings.store_location) as store:
        cam, camera_name = resolve_camera(camera_text, store)  # inline, or a camera registered in the cache
        opts = estimate_options(args.options, cam, camera_name, store)  # its plane as the default
        if args.overlay_out:
            opts.overlay = True
        check_robot_pose(cam, opts, camera_name)
        record = _ensure_built(args, settings, store)
        bank = store.ready_bank(record)  # 409 with the reason if the build failed
        result = estimate_result(record, bank, image.read_bytes(), cam, opts,
                                 max_pixels=settings.max_image_pixels, camera_name=camera_name,
                                 grasps=grasps_of(store.grasps(record["id"])),
                                 default_deadline_ms=settings.deadline_ms,
                                 appearance=appearance_of(store, record, bank))  # its reference photos
    if args.overlay_out and result.overlay_png_base64 is not None:
        Path(args.overlay_out).write_bytes(base64.b64decode(result.overlay_png_base64))
        result.overlay_png_base64 = None
        print(f"overlay written to {args.overlay_out}", file=sys.stderr)
    print(result.model_dump_json(indent=2))
    return 0


def cmd_worker(args: argparse.Namespace) -> int:
    from service.jobs.queue import worker_main
    from service.logs import configure
    from service.settings import Settings

    # no threads.configure here: each job's forked horse sets its thread budget (numba, then fork: unsafe)
    settings = Settings(**({"cache_dir": args.cache_dir} if args.cache_dir else {}))
    configure(settings.log_level)
    return worker_main(settings, burst=args.burst)


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

    p = sub.add_parser("build", help="build a mesh's templates in this process, calibrate it for a plane "
                       "(POSE_PLANE_CALIBRATION_SCENES); print its ModelInfo JSON")
    _mesh_args(p)
    p.set_defaults(func=cmd_build)

    p = sub.add_parser("estimate", help="estimate a pose; print the API's EstimateResult JSON")
    _mesh_args(p)
    p.add_argument("image", help="PNG, JPEG, BMP or TIFF image")
    p.add_argument("--camera", required=True, help='intrinsics JSON file (e.g. examples/cam.json) or text: '
                   '{"fx","fy","cx","cy"}, or {"name": "<camera registered in the cache>"}')
    p.add_argument("--options", default=None, help='JSON text, e.g. {"distance_mm": 500}')
    p.add_argument("--overlay-out", default=None, metavar="PNG",
                   help="write the overlay (contours, axes, verdict) to this PNG file, not base64 in JSON")
    p.set_defaults(func=cmd_estimate)

    p = sub.add_parser("warm-up", help="compile the kernels into NUMBA_CACHE_DIR (what start-up does); "
                       "exit 1 if the synthetic part is not found")
    p.set_defaults(func=cmd_warm_up)

    p = sub.add_parser("worker", help="take template-build jobs from the shared store's queue "
                       "(POSE_STORE=redis://...); run one or more per machine")
    p.add_argument("--burst", action="store_true", help="stop when the queue is empty")
    p.set_defaults(func=cmd_worker)

    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except ServiceError as e:
        print(f"error ({e.status_code}): {e.detail}", file=sys.stderr)
        return 2
    except CliError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
