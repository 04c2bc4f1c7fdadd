"""Scale out: estimates per second with 1, 2 and 4 API processes on one Redis (loopback), and what the
Redis store adds to each estimate against the diskcache (p50, p95)::

    python bench/scale.py [--requests 6] [--latency-requests 20]

Starts its own redis-server (Debian's; AOF off: a benchmark) and uvicorn processes on 127.0.0.1
(``POSE_THREADS=1`` each, so N processes use N cores' worth of threads), builds the sprayer once
into each backend in this process, then: for N in 1, 2, 4, 2N clients spread round-robin over the N
ports post ``--requests`` estimates each (the paper frame); then, against one process per backend,
``--latency-requests`` sequential estimates, and the store accesses an estimate makes (record,
bank, grasps) 2,000 times in-process. Every loop is bounded; every process is stopped at the end.
On a shared 2-core machine more processes than cores only queue: read the rows as the shape.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data"
GRID = {"tilt_step_deg": 15, "view_step_deg": 45}
START_WAIT_S = 120

from service.jobs.build import register_upload, run_build  # noqa: E402
from service.settings import Settings  # noqa: E402
from service.stores import open_store  # noqa: E402
from tests.redis_server import RedisServer, free_port  # noqa: E402


def start_api(env: dict[str, str], log: Path) -> tuple[subprocess.Popen, str]:
    port = free_port()
    with open(log, "ab") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "service.main:create_app", "--factory", "--host", "127.0.0.1",
             "--port", str(port), "--log-level", "warning"],
            cwd=ROOT, env={**env, "POSE_PORT": str(port)}, stdout=out, stderr=subprocess.STDOUT,
            start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + START_WAIT_S
    while True:
        try:
            if httpx.get(f"{url}/health", timeout=2).status_code == 200:
                return proc, url
        except httpx.TransportError:
            pass
        if time.monotonic() > deadline or proc.poll() is not None:
            raise SystemExit(f"uvicorn did not start; see {log}")
        time.sleep(0.2)


def stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


def build(location: str, mesh: bytes) -> str:
    settings = Settings(store=location if location.startswith("redis://") else None,
                        cache_dir=Path(location), template_grid=GRID)
    with open_store(settings.store_location) as store:
        record, _ = register_upload(store, settings, mesh, filename="sprayer.stl", symmetry="y")
    assert run_build(settings.store_location, record["id"], 30.0) == "ready"
    return record["id"]


def post(client: httpx.Client, url: str, mid: str, frame: dict) -> float:
    t0 = time.perf_counter()
    r = client.post(f"{url}/models/{mid}/estimate", files={"image": ("0001.png", frame["image"])},
                    data={"camera": frame["camera"], "options": frame["options"]})
    r.raise_for_status()
    return time.perf_counter() - t0


def throughput(urls: list[str], mid: str, frame: dict, requests: int) -> float:
    clients = 2 * len(urls)
    errors: list[BaseException] = []

    def run(i: int) -> None:
        try:
            with httpx.Client(timeout=300) as c:
                for k in range(requests):
                    post(c, urls[(i + k) % len(urls)], mid, frame)
        except BaseException as e:  # reported below
            errors.append(e)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(clients)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]
    return clients * requests / (time.perf_counter() - t0)


def store_access_ms(location: str, mid: str, n: int = 2000) -> np.ndarray:
    """What an estimate asks the store: its record, its bank (a version check and the LRU), its grasps."""
    out = np.empty(n)
    with open_store(location) as store:
        store.bank(mid)  # loaded once, as a warm replica has it
        for i in range(n):
            t0 = time.perf_counter()
            store.ready_bank(store.get(mid))
            store.grasps(mid)
            out[i] = (time.perf_counter() - t0) * 1000
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--requests", type=int, default=6, help="estimates per client in the throughput runs")
    ap.add_argument("--latency-requests", type=int, default=20)
    args = ap.parse_args()

    gt = json.loads((DATA / "paper" / "gt.jsonl").read_text().splitlines()[0])
    K = gt["K"]
    frame = {"image": (DATA / "paper" / gt["image"]).read_bytes(),
             "camera": json.dumps({"fx": K[0][0], "fy": K[1][1], "cx": K[0][2], "cy": K[1][2]}),
             "options": json.dumps({"distance_mm": float(gt["t_mm"][2])})}
    mesh = (DATA / "models" / "sprayer.stl").read_bytes()
    tmp = Path(tempfile.mkdtemp(prefix="posecell-scale-"))
    redis = RedisServer(tmp / "redis").start()
    procs: list[subprocess.Popen] = []
    try:
        disk_dir = str(tmp / "cache")
        mid = build(redis.url, mesh)
        assert build(disk_dir, mesh) == mid
        base = {k: v for k, v in os.environ.items() if not k.startswith("POSE_")}
        base.update({"POSE_THREADS": "1", "POSE_LOG_LEVEL": "warning",
                     "POSE_TEMPLATE_GRID": json.dumps(GRID)})

        print("| API processes (one Redis) | clients | estimates | estimates/s |")
        print("|---|---|---|---|")
        for n in (1, 2, 4):
            started = [start_api({**base, "POSE_STORE": redis.url}, tmp / f"api-{n}-{i}.log")
                       for i in range(n)]
            procs = [p for p, _ in started]
            urls = [u for _, u in started]
            with httpx.Client(timeout=300) as c:  # each process's first estimate loads the bank
                for u in urls:
                    post(c, u, mid, frame)
            rate = throughput(urls, mid, frame, args.requests)
            print(f"| {n} | {2 * n} | {2 * n * args.requests} | {rate:.2f} |")
            stop(procs)
            procs = []

        print()
        print("| backend | estimate over HTTP p50 / p95, ms | store accesses per estimate p50 / p95, ms |")
        print("|---|---|---|")
        rows = {}
        for name, env in (("diskcache", {"POSE_CACHE_DIR": disk_dir}), ("redis", {"POSE_STORE": redis.url})):
            proc, url = start_api({**base, **env}, tmp / f"latency-{name}.log")
            procs = [proc]
            with httpx.Client(timeout=300) as c:
                post(c, url, mid, frame)
                http_ms = np.array([post(c, url, mid, frame) * 1000 for _ in range(args.latency_requests)])
            stop(procs)
            procs = []
            access = store_access_ms(redis.url if name == "redis" else disk_dir, mid)
            rows[name] = (http_ms, access)
            print(f"| {name} | {np.percentile(http_ms, 50):.1f} / {np.percentile(http_ms, 95):.1f} | "
                  f"{np.percentile(access, 50):.3f} / {np.percentile(access, 95):.3f} |")
        r, d = rows["redis"][1], rows["diskcache"][1]
        added = [np.percentile(r, q) - np.percentile(d, q) for q in (50, 95)]
        print(f"\nadded by Redis per estimate (store accesses): p50 {added[0]:+.3f} ms, "
              f"p95 {added[1]:+.3f} ms")
    finally:
        stop(procs)
        redis.stop()
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
