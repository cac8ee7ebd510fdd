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

import heapq

import numpy as np


def watershed_ift(depth: np.ndarray, markers: np.ndarray, mask: np.ndarray | None = None,
                  max_region: float | None = None) -> np.ndarray | None:
    """Labels (H, W) of ``markers``' dtype: each pixel takes the marker reached along the path whose largest step
    ``|depth[p] - depth[q]|`` is smallest (Falcao, Stolfi and Lotufo's image foresting transform).

    ``depth`` (H, W): non-negative integers (scipy takes uint8 or uint16); ``markers`` (H, W): integers, positive
    for the objects' seeds, negative for background seeds (flooded after the objects'), 0 elsewhere. With
    ``mask`` (H, W, bool) and ``max_region``: None as soon as one object's final pixels inside ``mask`` outnumber
    ``max_region`` (a pixel's label is final once it leaves the queue), for a caller that would refuse such a
    region anyway."""
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
    first: dict[int, int] = {0: -1}
    last: dict[int, int] = {0: -1}

    def enqueue(m: int, p: int, back: bool) -> None:
        """Pixel ``p`` into cost ``m``'s queue: at its back (a background label) or its front (an object's)."""
        near, far, outward, inward = (last, first, prv, nxt) if back else (first, last, nxt, prv)
        end = near.get(m, -1)
        outward[p], inward[p] = end, -1
        if end != -1:
            inward[end] = p
        near[m] = p
        if far.get(m, -1) == -1:
            far[m] = p

    for j, label in enumerate(out):
        if label != 0:
            cost[j] = 0
            enqueue(0, j, label < 0)
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
        while first.get(level, -1) != -1:
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
                    if first.get(pc, -1) == p:
                        first[pc] = b
                    if last.get(pc, -1) == p:
                        last[pc] = a
                    if a != -1:
                        nxt[a] = b
                    if b != -1:
                        prv[b] = a
                enqueue(m, p, lv < 0)
                if m > level:
                    heapq.heappush(levels, m)
    return np.array(out, dtype=np.asarray(markers).dtype).reshape(H, W)
