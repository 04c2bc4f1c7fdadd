"""Load: 4 clients x 200 estimates against a real ``python -m service serve`` on a loopback port while
a template build runs; prints errors, latency p50/p95 and the resident memory of the server and its
children before and after::

    python bench/load.py [--clients 4] [--requests 200]

Traffic goes to 127.0.0.1 only; every loop is bounded in count, and the server is stopped at the end.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
GRID = {"tilt_step_deg": 15, "view_step_deg": 45}
SLOW_GRID = {"view_step_deg": 5}  # the build that runs meanwhile: symmetry none, ~1,600 views
START_WAIT_S = 120
BUILD_WAIT_S = 600


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def tree_rss_mb(pid: int) -> tuple[float, int]:
    """Resident memory of ``pid`` and its descendants, MB, and how many processes that is."""
    parents: dict[int, int] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, ValueError, IndexError):
            parents[int(stat.parent.name)] = int(stat.read_text().split(")")[-1].split()[1])
    tree, frontier = {pid}, [pid]
    while frontier:
        p = frontier.pop()
        kids = [c for c, pp in parents.items() if pp == p and c not in tree]
        tree.update(kids)
        frontier.extend(kids)
    total = 0
    for p in tree:
        with contextlib.suppress(OSError):
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1])
    return total / 1024.0, len(tree)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clients", type=int, default=4)
    ap.add_argument("--requests", type=int, default=200, help="estimates per client")
    args = ap.parse_args()

    gt = json.loads((DATA / "paper" / "gt.jsonl").read_text().splitlines()[0])
    image = (DATA / "paper" / gt["image"]).read_bytes()
    K = gt["K"]
    camera = json.dumps({"fx": K[0][0], "fy": K[1][1], "cx": K[0][2], "cy": K[1][2]})
    options = json.dumps({"distance_mm": float(gt["t_mm"][2])})
    sprayer = (DATA / "models" / "sprayer.stl").read_bytes()

    tmp = Path(tempfile.mkdtemp(prefix="posecell-load-"))
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("POSE_")}
    env.update({"POSE_CACHE_DIR": str(tmp / "cache"), "POSE_PORT": str(port), "POSE_LOG_LEVEL": "warning",
                "POSE_TEMPLATE_GRID": json.dumps(GRID)})
    log = open(tmp / "serve.log", "wb")  # noqa: SIM115
    server = subprocess.Popen([sys.executable, "-m", "service", "serve"], cwd=ROOT, env=env, stdout=log,
                              stderr=subprocess.STDOUT, start_new_session=True)
    client = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=120)
    try:
        deadline = time.monotonic() + START_WAIT_S
        while True:
            with contextlib.suppress(httpx.TransportError):
                if client.get("/health").status_code == 200:
                    break
            if server.poll() is not None or time.monotonic() > deadline:
                raise SystemExit(f"the server did not start; see {tmp / 'serve.log'}")
            time.sleep(0.2)
        r = client.post("/models", files={"file": ("sprayer.stl", sprayer)}, data={"symmetry": "y"})
        mid = r.json()["id"]
        deadline = time.monotonic() + BUILD_WAIT_S
        while client.get(f"/models/{mid}").json()["status"] != "ready":
            if time.monotonic() > deadline:
                raise SystemExit("the model did not build")
            time.sleep(0.2)
        # warm: the first estimates load the kernels
        for _ in range(3):
            client.post(f"/models/{mid}/estimate", files={"image": ("i.png", image)},
                        data={"camera": camera, "options": options})
        rss_before, procs_before = tree_rss_mb(server.pid)
        slow = client.post("/models", files={"file": ("slow.stl", sprayer)},
                           data={"symmetry": "none", "templates": json.dumps(SLOW_GRID)}).json()["id"]

        latencies: list[float] = []
        statuses: dict[int, int] = {}
        errors: list[str] = []
        lock = threading.Lock()
        peak = [0.0]

        def one_client() -> None:
            with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=120) as c:
                for _ in range(args.requests):
                    t0 = time.perf_counter()
                    try:
                        r = c.post(f"/models/{mid}/estimate", files={"image": ("i.png", image)},
                                   data={"camera": camera, "options": options})
                        code = r.status_code
                        ok = code == 200 and r.json()["found"]
                    except httpx.HTTPError as e:
                        code, ok = -1, False
                        with lock:
                            errors.append(repr(e))
                    dt = time.perf_counter() - t0
                    with lock:
                        latencies.append(dt)
                        statuses[code] = statuses.get(code, 0) + 1
                        if not ok and code != -1:
                            errors.append(f"{code}")

        def watch_memory(stop: threading.Event) -> None:
            while not stop.wait(0.5):
                peak[0] = max(peak[0], tree_rss_mb(server.pid)[0])

        stop = threading.Event()
        watcher = threading.Thread(target=watch_memory, args=(stop,))
        watcher.start()
        t_start = time.perf_counter()
        threads = [threading.Thread(target=one_client) for _ in range(args.clients)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        wall = time.perf_counter() - t_start
        stop.set()
        watcher.join()
        build = client.get(f"/models/{slow}").json()
        rss_after, procs_after = tree_rss_mb(server.pid)
        lat = np.array(latencies) * 1000
        n = len(latencies)
        print(f"clients x estimates: {args.clients} x {args.requests} = {n}, in {wall:.1f} s "
              f"({n / wall:.1f} /s); a template build ran meanwhile ({build['status']}, "
              f"progress {build['progress']:.2f} at the end)")
        print(f"statuses: {dict(sorted(statuses.items()))}; errors (not 200 + found): {len(errors)}")
        print(f"latency ms: p50 {np.percentile(lat, 50):.0f}, p95 {np.percentile(lat, 95):.0f}, "
              f"max {lat.max():.0f}")
        print(f"resident memory, server + children: before {rss_before:.0f} MB ({procs_before} processes), "
              f"peak {peak[0]:.0f} MB, after {rss_after:.0f} MB ({procs_after} processes)")
        return 0 if not errors else 1
    finally:
        client.close()
        server.send_signal(signal.SIGTERM)
        try:
            server.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
        log.close()


if __name__ == "__main__":
    sys.exit(main())
