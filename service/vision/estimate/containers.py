"""The containers the region merge (``segmentation._merge_kernel``) runs on, compiled: a binary heap of
(contrast, i, j) entries held in three arrays, ordered as Python orders tuples, and an open-addressing
int64 -> int64 hash table (numba's typed dict was 3x slower there)."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(inline="always")
def _less(hd, hi, hj, a, b):
    """Heap entry a before b: (contrast, i, j) compared as Python compares tuples."""
    if hd[a] != hd[b]:
        return hd[a] < hd[b]
    if hi[a] != hi[b]:
        return hi[a] < hi[b]
    return hj[a] < hj[b]


@nb.njit(inline="always")
def _swap(hd, hi, hj, a, b):
    hd[a], hd[b] = hd[b], hd[a]
    hi[a], hi[b] = hi[b], hi[a]
    hj[a], hj[b] = hj[b], hj[a]


@nb.njit
def _sift_up(hd, hi, hj, k):
    while k > 0:
        p = (k - 1) >> 1
        if _less(hd, hi, hj, k, p):
            _swap(hd, hi, hj, k, p)
            k = p
        else:
            break


@nb.njit
def _sift_down(hd, hi, hj, k, n):
    while True:
        c = 2 * k + 1
        if c >= n:
            break
        if c + 1 < n and _less(hd, hi, hj, c + 1, c):
            c += 1
        if _less(hd, hi, hj, c, k):
            _swap(hd, hi, hj, c, k)
            k = c
        else:
            break


@nb.njit
def _table(n):
    """An empty open-addressing table (keys, values) for ``n`` keys: 8 slots per key, a power of two;
    key -1: empty, -2: deleted."""
    cap = 16
    while cap < 8 * n:
        cap *= 2
    return np.full(cap, -1, np.int64), np.zeros(cap, np.int64)


@nb.njit(inline="always")
def _slot(key, mask):
    h = key * 0x9E3779B97F4A7C15  # Fibonacci hashing (wraps): neighbouring pair keys spread
    return (h ^ (h >> 29)) & mask


@nb.njit
def _find(hk, key):
    mask = hk.shape[0] - 1
    i = _slot(key, mask)
    while hk[i] != -1:
        if hk[i] == key:
            return i
        i = (i + 1) & mask
    return -1


@nb.njit
def _get(hk, hv, key):
    i = _find(hk, key)
    return hv[i] if i >= 0 else -1


@nb.njit
def _put(hk, hv, key, value):
    """Insert ``key`` (not present) into the first empty or deleted slot of its probe sequence."""
    mask = hk.shape[0] - 1
    i = _slot(key, mask)
    while hk[i] >= 0:
        i = (i + 1) & mask
    hk[i] = key
    hv[i] = value


@nb.njit
def _drop(hk, hv, key):
    hk[_find(hk, key)] = -2


@nb.njit
def _rehash(hk, hv):
    n = 0
    for q in range(hk.shape[0]):
        n += hk[q] >= 0
    k2, v2 = _table(n)
    for q in range(hk.shape[0]):
        if hk[q] >= 0:
            _put(k2, v2, hk[q], hv[q])
    return k2, v2
