"""The paper's scan-line border extraction (section II.A.2, Figs. 2-4): a reference implementation.

Clarity over speed; the service uses ``templates.border_at_pose`` (outer contour of a supersampled
silhouette), and the tests check that both give the same border on the paper's cases.

The procedure, as the paper describes it:

1. Project the template (every mesh node and the lines between them, eq. 6).
2. Through every node draw a horizontal and a vertical scan line. On each scan line keep the most
   minimum and most maximum points where the template's lines cross it (left/right on a horizontal
   line, top/bottom on a vertical one): the *node candidates* (Fig. 3).
3. Re-scan the candidates the same way (rows and columns one pixel apart), keeping the extremes.
4. Build the border line from the remaining points (here: chained greedily to the nearest
   unvisited point, Fig. 4).

The extremes along a line are the ends of the projected mesh's extent along it, so every kept
point lies on the outer border of the silhouette. The procedure cannot see parts of the border that
are not extreme along any row or column (the inner walls of a U seen from its open side), which the
contour method does see.
"""

from __future__ import annotations

import numpy as np

from service.vision.geometry.camera import as_intrinsics, project
from service.vision.geometry.frames import Pose

LINE_MERGE_PX = 0.25  # scan lines closer than this are one line


def project_nodes(vertices_mm, faces, pose: Pose, K) -> tuple[np.ndarray, np.ndarray]:
    """Projected nodes ``uv (V, 2)`` (pixels) and the template's lines ``edges (E, 2)`` (node indices)."""
    intr = as_intrinsics(K)
    uv = project(pose.apply(np.asarray(vertices_mm, float)), intr.K)
    F = np.asarray(faces, np.int64)
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    return uv, e


def _line_extremes(a: np.ndarray, b: np.ndarray, lines: np.ndarray, chunk: int = 64) -> np.ndarray:
    """For lines ``y = c`` (c in ``lines``) crossing segments with endpoints (x, y) ``a``/``b``, the
    (L, 2) min and max x of the crossings (nan where a line crosses nothing)."""
    out = np.full((len(lines), 2), np.nan)
    ya, yb = a[:, 1], b[:, 1]
    lo, hi = np.minimum(ya, yb), np.maximum(ya, yb)
    dy = yb - ya
    flat = dy == 0
    for i in range(0, len(lines), chunk):
        c = lines[i:i + chunk, None]  # (l, 1)
        hit = (lo[None, :] <= c) & (c <= hi[None, :])
        t = np.where(flat[None, :], 0.0, (c - ya[None, :]) / np.where(flat, 1.0, dy)[None, :])
        x = a[None, :, 0] + t * (b[None, :, 0] - a[None, :, 0])
        # A flat segment on the line contributes both of its ends.
        x_min = np.where(hit, np.where(flat[None, :], np.minimum(a[:, 0], b[:, 0])[None, :], x), np.inf)
        x_max = np.where(hit, np.where(flat[None, :], np.maximum(a[:, 0], b[:, 0])[None, :], x), -np.inf)
        mn, mx = x_min.min(axis=1), x_max.max(axis=1)
        ok = np.isfinite(mn)
        out[i:i + chunk][ok] = np.stack([mn[ok], mx[ok]], axis=1)
    return out


def _merge_lines(values: np.ndarray, tol: float) -> np.ndarray:
    """Sorted values, each at least ``tol`` above the previous kept one."""
    kept: list[float] = []
    for x in np.sort(np.asarray(values, float)):
        if not kept or x - kept[-1] >= tol:
            kept.append(float(x))
    return np.asarray(kept)


def scan_extremes(uv: np.ndarray, edges: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Extreme crossings of the template's lines with horizontal lines ``v = rows`` and vertical
    lines ``u = cols``: (M, 2) uv points (left/right and top/bottom ends)."""
    a, b = uv[edges[:, 0]], uv[edges[:, 1]]
    pts = []
    h = _line_extremes(a, b, rows)
    ok = np.isfinite(h[:, 0])
    pts += [np.stack([h[ok, 0], rows[ok]], 1), np.stack([h[ok, 1], rows[ok]], 1)]
    v = _line_extremes(a[:, ::-1], b[:, ::-1], cols)  # swap axes: lines u = c
    ok = np.isfinite(v[:, 0])
    pts += [np.stack([cols[ok], v[ok, 0]], 1), np.stack([cols[ok], v[ok, 1]], 1)]
    return np.concatenate(pts) if pts else np.zeros((0, 2))


def rescan(points: np.ndarray, bin_px: float = 1.0) -> np.ndarray:
    """Step 3: among the candidates, keep per row (and per column) bin the left/right (top/bottom) ones."""
    keep = np.zeros(len(points), bool)
    for axis in (1, 0):  # rows: extremes in u; columns: extremes in v
        key = np.floor(points[:, axis] / bin_px).astype(np.int64)
        other = points[:, 1 - axis]
        order = np.lexsort((other, key))
        k_sorted = key[order]
        first = np.concatenate([[True], k_sorted[1:] != k_sorted[:-1]])
        last = np.concatenate([k_sorted[1:] != k_sorted[:-1], [True]])
        keep[order[first]] = True
        keep[order[last]] = True
    return points[keep]


def chain(points: np.ndarray) -> np.ndarray:
    """Step 4: order the points into a line, always stepping to the nearest unvisited point."""
    from scipy.spatial import cKDTree

    n = len(points)
    if n < 3:
        return points
    tree = cKDTree(points)
    visited = np.zeros(n, bool)
    order = [int(np.argmin(points[:, 1]))]
    visited[order[0]] = True
    for _ in range(n - 1):
        p = points[order[-1]]
        k = 8
        while True:
            _, idx = tree.query(p, k=min(k, n))
            idx = np.atleast_1d(idx)
            free = idx[~visited[idx]]
            if len(free) or k >= n:
                break
            k *= 4
        if not len(free):
            break
        order.append(int(free[0]))
        visited[free[0]] = True
    return points[order]


def scanline_border(vertices_mm, faces, pose: Pose, K, *, rescan_bin_px: float = 1.0) -> np.ndarray:
    """The paper's border of the projected mesh: (M, 2) uv pixels, ordered along the border."""
    uv, edges = project_nodes(vertices_mm, faces, pose, K)
    rows = _merge_lines(uv[:, 1], LINE_MERGE_PX)
    cols = _merge_lines(uv[:, 0], LINE_MERGE_PX)
    candidates = scan_extremes(uv, edges, rows, cols)
    border = rescan(candidates, rescan_bin_px)
    return chain(border)
