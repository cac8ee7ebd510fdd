"""The image foresting transform watershed of :func:`scipy.ndimage.watershed_ift`, 4-connected, without scipy.

Splitting run-together blobs (:func:`~chic_register.detect.blobs.detect_blobs`)
floods a small window from its seeds. ``scipy.ndimage`` does this in C, but
importing it costs a third of a second, more than a one-shot volume solve spends
on everything else it imports; the windows hold a few hundred pixels, so the
same algorithm in Python costs a millisecond. It follows scipy's step for step
(``tests/detect/test_watershed.py`` holds it to scipy's output), quirks included:
neighbours are taken in the flattened array (a row's last pixel touches the next
row's first), an object label joins the front of its cost's queue and a
background label its back, and a queue holding only one element does not let go
of it when it moves.
"""

from __future__ import annotations

import hashlib
import heapq
from collections import OrderedDict

import numpy as np

#: Floods remembered (:func:`watershed_ift`): a volume's slices are detected up to three times (their own blob width,
#: the scan's, a noise-bounded level), and a component the same at each asks the same flood again.
REMEMBERED_FLOODS = 64
_floods: OrderedDict = OrderedDict()


def watershed_ift(depth: np.ndarray, markers: np.ndarray, mask: np.ndarray | None = None,
                  max_region: float | None = None) -> np.ndarray | None:
    """Labels (H, W) of ``markers``' dtype: each pixel takes the marker reached along the path whose largest step
    ``|depth[p] - depth[q]|`` is smallest (Falcao, Stolfi and Lotufo's image foresting transform).

    ``depth`` (H, W): non-negative integers (scipy takes uint8 or uint16); ``markers`` (H, W): integers, positive
    for the objects' seeds, negative for background seeds (flooded after the objects'), 0 elsewhere. With
    ``mask`` (H, W, bool) and ``max_region``: None when one object's pixels inside ``mask`` outnumber
    ``max_region`` (the flood stops as soon as they do), for a caller that would refuse such a region anyway.

    The last :data:`REMEMBERED_FLOODS` floods are remembered by their inputs: a flood finished answers any
    ``max_region``, one stopped answers a smaller one.
    """
    depth, markers = np.asarray(depth), np.asarray(markers)
    limited = mask is not None and max_region is not None
    h = hashlib.blake2b(digest_size=16)
    for a in (depth, markers, np.asarray(mask, bool) if mask is not None else np.zeros(0, bool)):
        h.update(repr((a.shape, a.dtype.str)).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    key = h.digest()
    known = _floods.get(key)
    if known is not None:
        _floods.move_to_end(key)
        labels, stopped_at, largest = known
        if labels is None and limited and max_region <= stopped_at:
            return None
        if labels is not None:
            return None if limited and largest > max_region else labels.copy()
    labels = _flood(depth, markers, mask, max_region)
    if labels is None:
        _floods[key] = (None, max_region, None)
    else:
        largest = 0
        if mask is not None:
            inside = labels[np.asarray(mask, bool)]
            largest = int(np.bincount(inside[inside > 0]).max(initial=0))
        _floods[key] = (labels.copy(), None, largest)
    while len(_floods) > REMEMBERED_FLOODS:
        _floods.popitem(last=False)
    return labels


def forget_floods() -> None:
    """Empty :func:`watershed_ift`'s memory (a benchmark timing floods, a test of the memory)."""
    _floods.clear()


def _flood(depth: np.ndarray, markers: np.ndarray, mask: np.ndarray | None, max_region: float | None):
    """:func:`watershed_ift`'s flood, step for step as scipy's."""
    H, W = depth.shape
    size = H * W
    val = np.asarray(depth).ravel().astype(np.int64).tolist()
    out = np.asarray(markers).ravel().tolist()
    if size == 0:
        return np.asarray(markers).copy()
    maxval = max(val)
    cost = [maxval + 1] * size
    done = [False] * size
    nxt = [-1] * size
    prv = [-1] * size
    first = [-1] * (maxval + 2)  # each cost's queue: its first and last pixel, linked through nxt and prv
    last = [-1] * (maxval + 2)

    marked = np.asarray(markers).ravel() != 0
    # a background seed whose neighbours are all seeds changes nothing when it leaves the queue (every neighbour
    # already costs 0): it keeps its label without ever being queued, which leaves the others' order as it was
    quiet = marked.copy()
    for off in (-W, -1, 1, W):
        shifted = np.ones(size, bool)
        if off > 0:
            shifted[:size - off] = marked[off:]
        else:
            shifted[-off:] = marked[:size + off]
        quiet &= shifted
    queued = np.flatnonzero(marked & ~(quiet & (np.asarray(markers).ravel() < 0))).tolist()
    for j in np.flatnonzero(marked).tolist():
        cost[j] = 0
    # the seeds' queue (cost 0) as scipy builds it: each object seed joins its front, each background seed its back
    seeds = [j for j in reversed(queued) if out[j] > 0] + [j for j in queued if out[j] < 0]
    for a, b in zip(seeds, seeds[1:]):
        nxt[a], prv[b] = b, a
    if seeds:
        first[0], last[0] = seeds[0], seeds[-1]
    inside = np.asarray(mask).ravel().tolist() if mask is not None and max_region is not None else None
    counts: dict[int, int] = {}
    offsets = (-W, -1, 1, W)
    levels = [0]  # the costs whose queues may hold pixels (a queue below the current cost is never visited again)
    level = -1
    while levels:
        nxt_level = heapq.heappop(levels)
        if nxt_level <= level:
            continue
        level = nxt_level
        while first[level] != -1:
            v = first[level]
            first[level] = nxt[v]
            if nxt[v] != -1:
                prv[nxt[v]] = -1
            prv[v] = nxt[v] = -1
            cv, lv, xv = cost[v], out[v], val[v]
            if inside is not None and not done[v] and lv > 0 and inside[v]:
                counts[lv] = counts.get(lv, 0) + 1
                if counts[lv] > max_region:
                    return None
            done[v] = True
            for off in offsets:
                p = v + off
                if p < 0 or p >= size or done[p]:
                    continue
                w = abs(val[p] - xv)
                m = cv if cv > w else w
                pc = cost[p]
                if m >= pc:
                    continue
                cost[p] = m
                out[p] = lv
                if nxt[p] != -1 or prv[p] != -1:  # out of the queue it was in
                    a, b = prv[p], nxt[p]
                    if first[pc] == p:
                        first[pc] = b
                    if last[pc] == p:
                        last[pc] = a
                    if a != -1:
                        nxt[a] = b
                    if b != -1:
                        prv[b] = a
                # into cost m's queue: a background label at its back, an object's at its front
                near, far, outward, inward = (last, first, prv, nxt) if lv < 0 else (first, last, nxt, prv)
                e = near[m]
                outward[p], inward[p] = e, -1
                if e != -1:
                    inward[e] = p
                near[m] = p
                if far[m] == -1:
                    far[m] = p
                if m > level:
                    heapq.heappush(levels, m)
    return np.array(out, dtype=np.asarray(markers).dtype).reshape(H, W)
