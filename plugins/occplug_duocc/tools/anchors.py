"""K-means anchors for the image-to-query detector, from the training split's ground-truth boxes.

The public code (Sparse4D's ``tools/anchor_generator.py``, writing ``nuscenes_kmeans900_42m.npy``) starts its 900 queries at
the k-means centres of the ego-frame box centres within 42 m, every anchor with the log of the mean box size and
yaw 0. :func:`kmeans_anchors` does the same on any ``(M, 3)`` set of centres; ``python -m occplug_duocc.tools.fit_anchors``
collects them from a config's training split and writes a config overlay that sets the detector's
``anchor_centres`` and ``anchor_size``.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["kmeans", "kmeans_anchors"]


def kmeans(points: Tensor, k: int, *, iterations: int = 100, seed: int = 0) -> Tensor:
    """Lloyd's k-means with k-means++ seeding (deterministic for a seed).

    Args:
        points: ``(M, D)`` float points, ``M >= k``.
        k: number of clusters.
        iterations: at most this many Lloyd steps (stops earlier once no assignment changes).
        seed: generator seed of the k-means++ draws.

    Returns:
        ``(k, D)`` float64 cluster centres, sorted by their first coordinate then the second (a stable order, so
        the same data always gives the same anchor per query). An empty cluster is re-seeded at the point
        farthest from its centre.
    """
    if points.dim() != 2 or points.shape[0] < k or k < 1:
        raise ValueError(f"kmeans: need (M, D) points with M >= k >= 1, got {tuple(points.shape)} for k={k}")
    x = points.to(torch.float64)
    gen = torch.Generator().manual_seed(seed)
    chosen = [int(torch.randint(x.shape[0], (1,), generator=gen))]
    d2 = (x - x[chosen[0]]).square().sum(1)  # squared distance to the nearest chosen centre, kept as a running min
    for _ in range(1, k):  # k-means++: the next centre with probability proportional to d2
        if float(d2.sum()) == 0.0:
            chosen.append(int(torch.randint(x.shape[0], (1,), generator=gen)))
        else:
            chosen.append(int(torch.multinomial(d2, 1, generator=gen)))
        d2 = torch.minimum(d2, (x - x[chosen[-1]]).square().sum(1))
    centres = x[chosen].clone()
    assign = torch.full((x.shape[0],), -1, dtype=torch.long)
    for _ in range(iterations):
        new = _nearest(x, centres)
        if torch.equal(new, assign):
            break
        assign = new
        counts = torch.bincount(assign, minlength=k)
        sums = torch.zeros_like(centres).index_add_(0, assign, x)
        filled = counts > 0
        centres[filled] = sums[filled] / counts[filled, None]
        for c in torch.nonzero(~filled).flatten().tolist():  # re-seed an empty cluster at the worst-fitted point
            worst = int((x - centres[assign]).norm(dim=1).argmax())
            centres[c] = x[worst]
            assign[worst] = c
    order = sorted(range(k), key=lambda i: tuple(centres[i].tolist()))
    return centres[order]


def _nearest(x: Tensor, centres: Tensor, chunk: int = 8192) -> Tensor:
    """Index of the nearest centre for each point, ``chunk`` points at a time (bounded memory)."""
    return torch.cat([torch.cdist(x[i : i + chunk], centres).argmin(1) for i in range(0, x.shape[0], chunk)])


def kmeans_anchors(boxes: Tensor, k: int, *, seed: int = 0) -> tuple[Tensor, Tensor]:
    """Anchor centres and size as the public code makes them.

    Args:
        boxes: ``(M, >= 6)`` ego-frame boxes ``[cx, cy, cz, l, w, h, ...]`` (metres), ``M >= k``.
        k: number of anchors (the detector's ``num_queries``).
        seed: k-means++ seed.

    Returns:
        ``centres (k, 3)`` (k-means of the box centres) and ``size (3,)``: the mean ``(l, w, h)`` over all boxes
        (the code stores its log; the detector takes metres and logs it).
    """
    if boxes.dim() != 2 or boxes.shape[1] < 6:
        raise ValueError(f"kmeans_anchors: boxes must be (M, >= 6), got {tuple(boxes.shape)}")
    return kmeans(boxes[:, :3], k, seed=seed), boxes[:, 3:6].to(torch.float64).mean(0)
