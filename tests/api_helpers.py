"""Helpers the in-process API tests share (TestClient against create_app)."""

from __future__ import annotations

import time

BUILD_WAIT_S = 300  # give up polling a build after this long (a hang guard, not a speed assert)


def wait_built(client, mid: str, seen: list | None = None) -> dict:
    """Poll ``GET /models/{mid}`` until the build is ready or failed; every answer goes to ``seen``."""
    deadline = time.monotonic() + BUILD_WAIT_S
    while time.monotonic() < deadline:
        info = client.get(f"/models/{mid}").json()
        if seen is not None:
            seen.append(info)
        if info["status"] in ("ready", "failed"):
            return info
        time.sleep(0.1)
    raise AssertionError(f"model {mid} still {info['status']} after {BUILD_WAIT_S} s")
