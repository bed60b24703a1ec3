"""Two-sided chamfer distance between recent events and a rendered model's edges: a global alignment cost.

The tracker's template score (a template correlated with the EROS) is only locally meaningful: poses several
centimetres off can score as high as the truth. The chamfer cost compares **where the edges are**:

- ``model_to_events``: the mean distance from each model edge pixel to the nearest recent event (a distance
  transform of the event image, computed once per observation);
- ``events_to_model``: the mean distance from each recent event of a fixed region to the nearest model edge,
  each distance truncated at ``cap`` (an event no edge explains costs ``cap``, whatever the pose).

Both are means over a set the pose does not choose (its own edges; the region's events), so a silhouette cannot
win by shrinking (fewer events explained) or growing (more edges without events). The cost is in pixels of the
image it is computed on; lower is better; the truth of a clean observation costs about the events' spread.

Model edges (:func:`model_edges`) are the silhouette's boundary, depth steps inside it and shading steps (the
creases of a box), from a depth/grey render (:class:`~torchevtrack.raster.RasterRenderer`). Recent events
(:func:`recent_events`) are the pixels of a time surface fired within ``window_us`` of ``t_now`` with at least
``min_support`` recent neighbours (isolated noise events dropped).

Arrays here are numpy (the functional core of :class:`~torchevtrack.stages.relocalise.Relocaliser`).

Example:
    >>> import numpy as np
    >>> edges = np.zeros((20, 20), bool); edges[5:15, 5] = True
    >>> events = np.zeros((20, 20), bool); events[5:15, 7] = True
    >>> round(chamfer(edges, events, distance_map(events, 10.0), 10.0), 2)
    2.0
"""

from __future__ import annotations

import numpy as np
import torch
from scipy import ndimage

__all__ = ["chamfer", "distance_map", "model_edges", "recent_events"]


def recent_events(last_us: torch.Tensor, t_now_us: int, window_us: int, min_support: int = 1) -> np.ndarray:
    """Pixels that fired within ``window_us`` before ``t_now_us`` and have ``min_support`` such neighbours.

    Args:
        last_us: ``(H, W)`` or ``(C, H, W)`` int64 time surface (microseconds, newest event per pixel and channel).
        t_now_us: the observation time; window_us: the recency window (microseconds, > 0).
        min_support: recent pixels required among the 8 neighbours (0 keeps isolated ones).
    Returns: ``(H, W)`` bool.
    """
    if window_us <= 0:
        raise ValueError(f"window_us must be positive, got {window_us}")
    last = torch.as_tensor(last_us)
    if last.ndim == 3:
        last = last.amax(0)
    if last.ndim != 2:
        raise ValueError(f"last_us must be (H, W) or (C, H, W), got {tuple(last_us.shape)}")
    age = int(t_now_us) - last.numpy()
    mask = (age >= 0) & (age <= window_us)
    if min_support > 0:
        n = ndimage.convolve(mask.astype(np.uint8), np.ones((3, 3), np.uint8), mode="constant")
        mask &= n > min_support  # n counts the pixel itself
    return mask


def model_edges(depth: np.ndarray, gray: np.ndarray | None = None, gray_step: float = 0.05,
                depth_step: float = 0.05) -> np.ndarray:
    """Edge pixels of renders: silhouette boundary (object pixels with a background 4-neighbour), and object
    pixels whose depth differs from a 4-neighbour's by more than ``depth_step`` of its depth (occluding inner
    contours) or whose grey differs by more than ``gray_step`` (creases, texture).

    Shape: depth ``(..., h, w)`` float (0 off the object), gray the same or ``None`` -> ``(..., h, w)`` bool.
    """
    obj = depth > 0
    edge = np.zeros_like(obj)
    for axis in (-1, -2):
        for a, b in ((slice(1, None), slice(None, -1)), (slice(None, -1), slice(1, None))):
            ia = [slice(None)] * depth.ndim
            ib = [slice(None)] * depth.ndim
            ia[axis], ib[axis] = a, b
            ia, ib = tuple(ia), tuple(ib)
            step = ~obj[ib] | (np.abs(depth[ia] - depth[ib]) > depth_step * depth[ia])
            if gray is not None:
                step |= np.abs(gray[ia] - gray[ib]) > gray_step
            edge[ia] |= obj[ia] & step
    return edge


def distance_map(mask: np.ndarray, cap: float) -> np.ndarray:
    """Euclidean distance (pixels) from each pixel to the nearest ``True`` pixel of ``mask``, capped at ``cap``
    (all ``cap`` if the mask is empty). Shape: ``(h, w)`` bool -> ``(h, w)`` float32."""
    if not mask.any():
        return np.full(mask.shape, cap, np.float32)
    return np.minimum(ndimage.distance_transform_edt(~mask), cap).astype(np.float32)


def chamfer(edges: np.ndarray, events: np.ndarray, events_distance: np.ndarray, cap: float) -> float:
    """Two-sided chamfer cost (pixels) of one model edge image against an event image of the same region.

    ``(mean over edges of events_distance + mean over events of the capped distance to the edges) / 2``;
    ``events_distance`` is :func:`distance_map` of ``events`` (computed once per observation). A side with no
    pixels costs ``cap``.

    Shape: edges, events ``(h, w)`` bool, events_distance ``(h, w)`` float -> float.
    """
    a = float(events_distance[edges].mean()) if edges.any() else cap
    b = float(distance_map(edges, cap)[events].mean()) if events.any() else cap
    return 0.5 * (a + b)
