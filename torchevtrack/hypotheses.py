"""Two hypotheses per object: the tracker with its UKF and a twin without it, the better one kept.

On held-out data neither variant of the method holds more runs than the other, but they lose different runs: on
the wide suite's dev split the full method holds 81 of 128 runs and its UKF ablation 74, and one or the other holds
90 (docs/notebook.md, 2026-12-03). Where one of them has turned away from the object, the two differ in how well
they explain the same recent events, and that comparison does not need the absolute level of a cost, which varies
between scenes far more than between a right and a wrong pose.

With ``config.hypotheses.enabled`` an :class:`~torchevtrack.tracker.EventPoseTracker` keeps a twin of itself with
the UKF off (``tracker.twin``), updated after it with the same windows. :class:`Hypotheses` runs after both updates; every
``period_us`` of event time per element it costs the two poses against the same recent events
(:meth:`~torchevtrack.stages.relocalise.Relocaliser.costs`, the two-sided chamfer distance in pixels) and
:func:`arbitrate` counts the checks in a row in which each was clearly better (its rival's cost above ``ratio``
times its own). After ``patience`` of them the winner is the element's output (:attr:`Hypotheses.chosen`) and
the loser takes the winner's motion state (:meth:`~torchevtrack.tracker.EventPoseTracker.adopt`): both go on from
the better pose. The tracker's output is then the chosen hypothesis's pose (:meth:`Hypotheses.output`).

The twin shares the tracker's event stages (EROS, time surface, flow: they depend on the events only) and doubles
the rest of an update; each check renders both poses at full resolution. Streaming, a run takes about 2.3x the time
of one tracker and a check's update about 5 ms more (docs/benchmarks.md).

Example:
    >>> import torch
    >>> from torchevtrack.hypotheses import arbitrate
    >>> run = torch.zeros(3, 2, dtype=torch.int64)
    >>> costs = torch.tensor([[1.0, 2.0], [1.0, 1.1], [3.0, 1.0]], dtype=torch.float64)  # px, (B, 2)
    >>> arbitrate(costs, run, ratio=1.25, patience=2).tolist(), run.tolist()
    ([-1, -1, -1], [[1, 0], [0, 0], [0, 1]])
    >>> arbitrate(costs, run, ratio=1.25, patience=2).tolist(), run.tolist()
    ([0, -1, 1], [[0, 0], [0, 0], [0, 0]])
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np
import torch
import trimesh
from torch import nn

from torchevtrack.camera import Camera
from torchevtrack.raster import RasterRenderer
from torchevtrack.stages import batch_mask
from torchevtrack.stages.relocalise import Relocaliser

if TYPE_CHECKING:  # the tracker imports this module: no import cycle at run time
    from torchevtrack.config import HypothesesConfig
    from torchevtrack.tracker import EventPoseTracker

__all__ = ["Hypotheses", "arbitrate"]


def arbitrate(costs: torch.Tensor, run: torch.Tensor, ratio: float, patience: int) -> torch.Tensor:
    """One comparison of two hypotheses per element.

    Args:
        costs: ``(B, 2)`` float64 the two hypotheses' costs (lower is better) against the same observation.
        run: ``(B, 2)`` int64, updated in place: per hypothesis, the checks in a row in which it was clearly better
            (the other's cost above ``ratio`` times its own); an element's run restarts when it has a winner.
        ratio: ``> 1``; patience: ``>= 1`` checks.

    Returns:
        ``(B,)`` int64: the hypothesis (0 or 1) that has now been clearly better for ``patience`` checks in a row, or
        -1 (no change).
    """
    clear = torch.stack((costs[:, 1] > ratio * costs[:, 0], costs[:, 0] > ratio * costs[:, 1]), 1)
    run.copy_(torch.where(clear, run + 1, 0))
    won = run >= patience  # at most one per row: both clearly better is impossible with ratio > 1
    winner = torch.where(won[:, 0], 0, torch.where(won[:, 1], 1, -1))
    run[winner >= 0] = 0
    return winner


class Hypotheses(nn.Module):
    """Keep the better of two hypotheses per element (module docstring).

    Args:
        scorers: one :class:`~torchevtrack.stages.relocalise.Relocaliser` per distinct mesh (its :meth:`costs`).
        owner: ``B`` indices into ``scorers``, the mesh of each element.
        ratio: a hypothesis is clearly better when the other's cost exceeds ``ratio`` times its own.
        patience: checks in a row a hypothesis must be clearly better to win.
        period_us: event time between two checks of an element.

    Buffers (``B`` elements):
        chosen: ``(B,)`` int64, the output hypothesis: 0 the tracker, 1 its twin.
        run: ``(B, 2)`` int64, :func:`arbitrate`'s counts.
        next_us: ``(B,)`` int64, the event time of the next check (-1: one period after the next update).
        costs: ``(B, 2)`` float64, each element's last check's costs (pixels; NaN before its first check).

    ``forward(tracker, twin, t_us)`` after both updated (``t_us`` ``(B,)`` int64 or an int: the update's time)
    compares the elements that are due and lets each loser :meth:`~torchevtrack.tracker.EventPoseTracker.adopt` its
    winner's state; :meth:`output` gives the chosen poses ``(B, 7)``. :attr:`checks` and :attr:`switches` count
    the comparisons and the adoptions.
    """

    def __init__(self, scorers: Sequence[Relocaliser], owner: Sequence[int], *, ratio: float = 1.5,
                 patience: int = 2, period_us: int = 20_000):
        super().__init__()
        if not ratio > 1 or int(patience) < 1 or int(period_us) <= 0:
            raise ValueError(f"need ratio > 1, patience >= 1 and period_us > 0, got {ratio}, {patience}, {period_us}")
        self.scorers, self.owner = list(scorers), [int(i) for i in owner]
        self.ratio, self.patience, self.period_us = float(ratio), int(patience), int(period_us)
        B = len(self.owner)
        self.register_buffer("chosen", torch.zeros(B, dtype=torch.int64))
        self.register_buffer("run", torch.zeros(B, 2, dtype=torch.int64))
        self.register_buffer("next_us", torch.full((B,), -1, dtype=torch.int64))
        self.register_buffer("costs", torch.full((B, 2), float("nan"), dtype=torch.float64))
        self.checks = self.switches = 0

    @classmethod
    def from_config(cls, cfg: "HypothesesConfig", camera: Camera, meshes: Sequence[trimesh.Trimesh],
                    owner: Sequence[int], radii: Sequence[float]) -> "Hypotheses":
        """One scorer per distinct loaded mesh of ``meshes`` with its bounding radius of ``radii`` (metres); ``owner``
        gives each of the ``B`` elements its mesh. The scorers observe one event pixel per model edge pixel, the
        window the ratio and patience were chosen with."""
        scorers = [Relocaliser(RasterRenderer(mesh, camera), radius, events_per_edge=1.0)
                   for mesh, radius in zip(meshes, radii)]
        return cls(scorers, owner, ratio=cfg.ratio, patience=cfg.patience, period_us=cfg.period_us)

    def reset(self, mask: torch.Tensor | None = None) -> None:
        """Restart the elements of ``mask`` (default all; ``(B,)`` bool or ``(K,)`` indices): the tracker's own
        hypothesis chosen, no run, the first check one period after the next update."""
        m = batch_mask(mask, len(self.owner))
        self.chosen[m] = 0
        self.run[m] = 0
        self.next_us[m] = -1
        self.costs[m] = float("nan")

    def forward(self, tracker: "EventPoseTracker", twin: "EventPoseTracker", t_us: torch.Tensor | int) -> None:
        # most updates check nothing: that test in numpy, on the buffer's view
        t = np.asarray(t_us, dtype=np.int64)
        next_us = self.next_us.numpy()
        if next_us.min() < 0:  # the first update after a reset: the first check one period on
            next_us[:] = np.where(next_us < 0, t + self.period_us, next_us)
        due = t >= next_us
        if due.any():
            t = np.broadcast_to(t, due.shape)
            self._check(tracker, twin, torch.from_numpy(t.copy()), np.flatnonzero(due).tolist())

    @torch.inference_mode()
    def _check(self, tracker: "EventPoseTracker", twin: "EventPoseTracker", t: torch.Tensor, due: list[int]) -> None:
        """Cost both hypotheses of the ``due`` elements (``t`` ``(B,)`` int64 us) and arbitrate."""
        B = len(self.owner)
        surface = tracker.last_event_us
        costs = torch.stack([self.scorers[self.owner[i]].costs(torch.stack((tracker.pose[i], twin.pose[i])),
                                                                 surface[i], int(t[i])) for i in due])  # (K, 2)
        idx = torch.tensor(due)
        self.costs[idx] = costs
        self.next_us[idx] = t[idx] + self.period_us
        self.checks += len(due)
        run = self.run[idx]
        winner = torch.full((B,), -1, dtype=torch.int64)
        winner[idx] = arbitrate(costs, run, self.ratio, self.patience)
        self.run[idx] = run
        if bool((winner == 0).any()):
            twin.adopt(tracker, winner == 0)
        if bool((winner == 1).any()):
            tracker.adopt(twin, winner == 1)
        self.chosen.copy_(torch.where(winner >= 0, winner, self.chosen))
        self.switches += int((winner >= 0).sum())

    def output(self, tracker: "EventPoseTracker", twin: "EventPoseTracker") -> torch.Tensor:
        """The chosen hypothesis's pose per element, ``(B, 7)`` float64 (a new tensor)."""
        return torch.where(self.chosen[:, None] == 1, twin.pose, tracker.pose)

    def close(self) -> None:
        """Release the scorers' renderers."""
        for s in self.scorers:
            s.renderer.close()

    def extra_repr(self) -> str:
        return f"batch_size={len(self.owner)}, ratio={self.ratio}, patience={self.patience}, " \
               f"period_us={self.period_us}"
