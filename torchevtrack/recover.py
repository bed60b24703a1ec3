"""Finding a lost object again: the loss detector's verdict, a wide search, a masked restart.

:class:`Recoverer` runs after each tracker update (``config.recover``, with ``config.loss``) and reads only what the
tracker shows: its output :attr:`~torchevtrack.tracker.EventPoseTracker.pose`, its loss detector's state
(:class:`~torchevtrack.loss.LossDetector` ``lost`` and ``low_run``), its UKF's twist and its time surface (the
``time_surface`` stage where the tracker keeps one, else the flow's); it restarts elements with the tracker's
masked :meth:`~torchevtrack.tracker.EventPoseTracker.reset`. Per batch element:

* **Last good state.** After every confident update (the detector's ``low_run`` is 0) of an element that is not
  lost, its pose is the *good pose* and its time the *good time*; its *good twist* is the constant twist between two
  good poses at least ``TWIST_SPAN_US`` apart (:func:`~torchevtrack.stages.propagate.twist_between`).
* **Lost.** When the detector declares the element lost (``newly_lost``), it stays lost here until a search restarts
  it or confirms its pose (or a :meth:`~torchevtrack.tracker.EventPoseTracker.reset`): the detector's own "found
  again" is not trusted, as a tracker locked onto the wrong pose scores well against its own reference. The tracker
  keeps tracking meanwhile and its output stays its own pose, flagged lost (a false alarm then costs nothing; the
  good pose stays in :attr:`good_pose`). At the declaration, ``retry_us`` of event time later, then at intervals
  doubling up to ``MAX_RETRY_US``, each time once at least ``min_events`` pixels of its time surface fired within the
  last ``retry_us`` beside another such pixel (the search needs the object's recent edges: none in a blackout or
  with the object out of view, and isolated noise events do not count), the
  :class:`~torchevtrack.stages.relocalise.Relocaliser` searches around the good pose moved on by the good twist
  over the time since, at most ``MAX_EXTRAPOLATION_US`` (:func:`~torchevtrack.stages.propagate.propagate`), against
  the tracker's time surface, and costs the tracker's own pose too. Where it neither restarts nor confirms (below)
  and the tracker's own pose costs less than its result (the tracker kept following the object while flagged, and
  the extrapolated centre is the worse guess), a second search is centred on the tracker's pose. Where that fails
  too, the object may be back elsewhere in the frame (it left the view, or moved far in a blackout): the relocaliser's
  frame scan (:meth:`~torchevtrack.stages.relocalise.Relocaliser.scan`, the good pose's depth and rotation tried
  over the whole frame) gives a candidate, and a search centred on it is judged the same way. A ``clear``
  result that beats the tracker's pose, in view and within the search's depth reach (:func:`found_again`), restarts
  the element there (twist zero); where the search finds nothing better than a pose of the tracker's that costs at
  most the clear-winner cost (:func:`confirms`), the element is found again as it is.
* **Depth check** (``check_us``; 0: off). Every ``check_us`` of event time from each (re)start, an element that is
  not lost, and whose bounding sphere projects wholly inside the frame (:func:`wholly_in_view`), has its pose
  compared with its depth rivals (:meth:`~torchevtrack.stages.relocalise.Relocaliser.rivals`: the pose 20 % nearer
  and 25 % farther along its line of sight, each at its best image shift, by the coarse chamfer cost). Where a rival
  costs ``check_margin_px`` less than the pose, the tracker has drifted in depth, which its template score does not
  show (a smaller outline inside the object's events scores as well: on a 1280x720 turn the score read 17-27 with
  the estimate 30 cm too far, 8-15 while held): the element is flagged ``drifted`` until a later check finds no such
  rival (or a restart), and the tracker's lost flags show it. The flag only reports: it sets off no search, as
  searches set off by it restarted held runs at wrong poses on held-out data, and a search around the cheaper rival
  held no more runs (docs/notebook.md, 2026-12-07 evening and night).
* **Start search** (``start_search``): ``start_after_us`` after each (re)start, once the time surface holds that
  much of the object's motion, one search around the tracker's pose then; a result that beats both its runner-up and
  the tracker's pose by ``START_MARGIN_PX`` (:func:`beats_start`) restarts the element there, with the twist the UKF
  measured meanwhile (from a rough start pose, the local tracker alone may never reach the basin of the true one).
  Where it does not, the tracker's pose turned by ``TURN_DEG`` about each camera axis (:func:`turned_poses`), each
  refined by the template correction (:meth:`~torchevtrack.tracker.EventPoseTracker.refine`), restarts the element at
  the best if its template score beats the tracker's own pose, refined the same way, by ``TURN_MARGIN`` of it.

A depth check costs about 3-8 ms (one low-resolution render of each of three poses and small FFTs). A search
runs inside the update and blocks it: about 0.3-1.5 s of wall time per search, and a lost element's
search that finds nothing scans the frame too (about 1 s more at 640x480, 3 s at 1280x720; the event time does not
advance meanwhile, so offline tracking gives the same poses however long it takes). :attr:`Recoverer.searches`,
:attr:`Recoverer.search_s` and :attr:`Recoverer.restarts` count them (:attr:`Recoverer.checks` the depth checks).

Example:
    >>> import torch
    >>> from torchevtrack import Camera, EventPoseTracker
    >>> from torchevtrack.config import TrackerConfig
    >>> cfg = TrackerConfig().replace(loss={"enabled": True}, recover={"enabled": True})
    >>> tracker = EventPoseTracker(Camera(64, 48, 60.0, 60.0, 31.5, 23.5), "box", cfg)
    >>> tracker.reset(torch.tensor([0.0, 0.0, 0.6, 1.0, 0.0, 0.0, 0.0]))
    >>> e = torch.zeros(0, dtype=torch.long)
    >>> for i in range(30):  # no events: lost after loss.patience updates, no search (no events to search in)
    ...     pose = tracker(e, e, e, e, t_us=2000 * (i + 1))
    >>> bool(tracker.lost[0]), tracker.recover.searches, round(pose[0, 2].item(), 4)
    (True, 0, 0.6)
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, NamedTuple, Sequence

import numpy as np
import torch
import trimesh
from torch import nn

from torchevtrack.camera import Camera
from torchevtrack.chamfer import recent_events
from torchevtrack.config import RecoverConfig
from torchevtrack.geometry import quat_exp, quat_mul
from torchevtrack.kernels import kernel
from torchevtrack.mesh import symmetry_axis
from torchevtrack.raster import RasterRenderer
from torchevtrack.stages import BufferViews, batch_mask
from torchevtrack.stages.propagate import propagate, twist_between_kernel
from torchevtrack.stages.relocalise import LEVELS, Level, Relocalisation, Relocaliser
from torchevtrack.stages.template import render_window

if TYPE_CHECKING:  # the tracker imports this module
    from torchevtrack.tracker import EventPoseTracker

__all__ = ["MAX_EXTRAPOLATION_US", "MAX_RETRY_US", "RecoverArrays", "Recoverer", "SEED_COST_PX", "START_MARGIN_PX",
           "TURN_DEG", "TURN_MARGIN", "TWIST_SPAN_US", "beats", "beats_start", "confirms", "found_again",
           "recover_step", "search_levels", "turned_poses", "wholly_in_view"]

TWIST_SPAN_US = 20_000  # the good twist is measured over at least this span (one update's pose difference is noise)
# the good pose is moved on by the good twist for at most this long: beyond, a constant twist is a guess that grows
# worse than none (blackouts of 200 ms on synthetic sequences: search centres up to 40 cm off without this cap)
MAX_EXTRAPOLATION_US = 100_000
# a lost element's searches that find nothing come ever further apart (retry_us, 2 retry_us, ...) up to this: a search
# blocks the update for 0.3-1.5 s of wall time, and on the wide dev split's davis346 sequences 77 of 77 searches found
# nothing (docs/notebook.md, 2026-12-02); 31 of them, 13.5 s, on one sequence of 1 s
MAX_RETRY_US = 320_000
# a start search restarts an element where its result costs this much less than both its runner-up and the tracker's
# pose (chamfer px): at the relocaliser's 0.5 px it restarted 3 of 256 dev runs started at the truth at a wrong pose
# (and rescued 1); at 1 px none of the 256 was held or lost otherwise (two moved by at most 0.05 cm) and the standard
# start trials (2 cm / 10 deg off) kept 34 of 40 within the bounds at 0.2 s against 35 (docs/notebook.md, 2026-12-05
# afternoon)
START_MARGIN_PX = 1.0
# the relocaliser refines more first-level seeds while none has reached this chamfer cost (px), whatever the
# clear-winner cost: at the clear-winner cost of 5 px, stopping at 5 px too left a start search on `c_08_mug_fast_hd`
# with one seed's basin and no distinct runner-up, and it restarted that run 42 deg off (docs/notebook.md, 2026-12-05
# evening)
SEED_COST_PX = 3.0
# where a start search's chamfer result does not restart the element, the tracker's pose turned by these angles
# (degrees, both ways about each camera axis), each refined by two template corrections, restarts it at the best
# if that scores above the tracker's own pose (refined the same way) by this fraction of the latter: the template
# score tells the truth's basin from a nearby wrong one where the chamfer cost, 48 ms after a start, often does not;
# on the dev pair's start trials 34 of 96 draws within the bounds at 0.2 s against 30 (a margin of 2 %: 32, wrong
# turns of round cans) and the standard eight's 35 of 40 as before (docs/notebook.md, 2026-12-06 late afternoon)
TURN_DEG = (10.0, 20.0)
TURN_MARGIN = 0.1


def turned_poses(pose: torch.Tensor, degrees: Sequence[float]) -> torch.Tensor:
    """``pose`` ``(7,)`` and the same pose turned by each of ``degrees`` both ways about each camera axis through the
    object's origin (``q' = exp(phi) q``, the position kept): ``(1 + 6 len(degrees), 7)`` float64, ``pose`` first."""
    out = [pose.double()]
    for axis in range(3):
        for deg in degrees:
            for sign in (1.0, -1.0):
                phi = torch.zeros(3, dtype=torch.float64)
                phi[axis] = sign * math.radians(deg)
                out.append(torch.cat((pose[:3].double(), quat_mul(quat_exp(phi), pose[3:].double()))))
    return torch.stack(out)


def beats(found: Relocalisation, margin_px: float) -> bool:
    """Whether a search's result (one element) costs at least ``margin_px`` less than the tracker's own pose."""
    return float(found.own_cost[0]) - float(found.cost[0]) >= margin_px


def beats_start(found: Relocalisation, margin_px: float) -> bool:
    """Whether a start search's result (one element) clearly beats both the runner-up and the tracker's own pose: by
    ``margin_px`` of the chamfer cost each. No cap on the cost itself, unlike a lost element's ``clear``: right after
    a start the recent events are few and smeared, the true pose itself costs 4-4.5 px on the standard
    ``potted_regular``."""
    return float(found.runner_up[0]) - float(found.cost[0]) >= margin_px and beats(found, margin_px)


def found_again(found: Relocalisation, centre: torch.Tensor, reloc: Relocaliser) -> bool:
    """Whether a lost element's search (one element, centred on ``centre`` ``(1, 7)``) restarts it: a clear result
    that beats the tracker's own pose (:func:`beats`), with the object's centre in view and its depth within
    ``2 reloc.depth_reach_m`` of the search centre's. A search's Gauss-Newton polish on an object half out of view
    (few edges, all at the border) can slide it metres away along the line of sight at a low cost: not a find."""
    x, y, z = (float(v) for v in found.pose[0, :3])
    cam = reloc.camera
    u, v = cam.fx * x / z + cam.cx, cam.fy * y / z + cam.cy
    return bool(found.clear[0]) and beats(found, reloc.min_margin_px) and 0 <= u < cam.width \
        and 0 <= v < cam.height and abs(z - float(centre[0, 2])) <= 2 * reloc.depth_reach_m


def confirms(found: Relocalisation, max_cost_px: float, margin_px: float) -> bool:
    """Whether a lost element's search confirms the tracker's own pose: it costs at most ``max_cost_px`` and the
    search found nothing ``margin_px`` better."""
    return float(found.own_cost[0]) <= max_cost_px and not beats(found, margin_px)


def wholly_in_view(pose: torch.Tensor, reloc: Relocaliser) -> bool:
    """Whether the object's bounding sphere at ``pose`` ``(1, 7)`` projects wholly inside ``reloc``'s frame (and lies
    beyond 1.5 radii in front of the camera). A depth check compares whole outlines: with part of the object out of
    view its rivals' costs mislead (a box leaving the view flagged, and restarted 8 cm off when flags set off searches;
    docs/notebook.md, 2026-12-07 evening)."""
    if not float(pose[0, 2]) > 1.5 * reloc.radius:
        return False
    u0, v0, w, h = (int(x) for x in render_window(pose, reloc.camera, reloc.radius, margin_px=0)[0])
    return u0 >= 0 and v0 >= 0 and u0 + w <= reloc.camera.width and v0 + h <= reloc.camera.height


def search_levels(search_m: float) -> tuple[Level, ...]:
    """The relocaliser's :data:`~torchevtrack.stages.relocalise.LEVELS` with the image-plane half-width and the depth
    offsets of every level scaled so that the first level's half-width is ``search_m`` metres (rotations and scales
    as they are)."""
    k = search_m / LEVELS[0].xy_m
    return tuple(Level(lv.rot_deg, tuple(dz * k for dz in lv.dz_m), lv.xy_m * k, lv.scale) for lv in LEVELS)


@kernel
def bookkeeping_kernel(t, period_us, pose, declared, low_run, lost, good_pose, good_us, anchor_pose, anchor_us, twist,
                       started, next_search, retry_in, pending, retry_us, start_after_us, due, starting, next_check,
                       check_us, checking):
    """One update's bookkeeping of :class:`Recoverer` (module docstring), in place, per element ``b`` of ``B``.

    Inputs: ``t`` ``(B,)`` int64 the update's times (us), ``period_us`` the tracker's window (us), ``pose``
    ``(B, 7)`` its output, the detector's ``declared`` (``newly_lost``) ``(B,)`` bool and ``low_run`` ``(B,)`` int64,
    ``retry_us`` and ``start_after_us``. State, updated: the Recoverer's buffers of the same names (``started``,
    ``next_search``, ``retry_in``, ``pending``: ``started_us``, ``next_search_us``, ``retry_in_us``,
    ``start_pending``, ``next_check_us``). Output: ``due`` (a lost element's search is due), ``starting`` (its start
    search is due, and no longer pending) and ``checking`` (its depth check is due; ``check_us`` 0: never) ``(B,)``
    bool.
    """
    dt = np.empty(1)
    for b in range(t.shape[0]):
        if started[b] < 0:  # the first update since a (re)start: its window began a period ago
            started[b] = good_us[b] = anchor_us[b] = t[b] - period_us
            next_check[b] = started[b] + check_us
        if declared[b] and not lost[b]:
            lost[b] = True
            next_search[b] = t[b]
            retry_in[b] = retry_us
        if not lost[b] and low_run[b] == 0:  # a confident update: the good pose, and over a span the good twist
            good_pose[b] = pose[b]
            good_us[b] = t[b]
            if t[b] - anchor_us[b] >= TWIST_SPAN_US:
                dt[0] = (t[b] - anchor_us[b]) * 1e-6
                twist_between_kernel(anchor_pose[b:b + 1], pose[b:b + 1], dt, twist[b:b + 1])
                anchor_pose[b] = pose[b]
                anchor_us[b] = t[b]
        due[b] = lost[b] and t[b] >= next_search[b]
        starting[b] = pending[b] and not lost[b] and t[b] - started[b] >= start_after_us
        if starting[b]:
            pending[b] = False
        checking[b] = check_us > 0 and not lost[b] and t[b] >= next_check[b]
        if checking[b]:
            next_check[b] = t[b] + check_us


class RecoverArrays(NamedTuple):
    """A :class:`Recoverer` as compiled kernels take it (:meth:`Recoverer.arrays`): numpy views of its buffers in
    :func:`bookkeeping_kernel`'s order, written in place, its ``retry_us`` and ``start_after_us``, and the last
    update's outputs ``due``, ``starting`` ``(B,)`` bool and ``may`` ``(1,)`` bool (:meth:`Recoverer.may_search`)."""

    lost: np.ndarray
    good_pose: np.ndarray
    good_us: np.ndarray
    anchor_pose: np.ndarray
    anchor_us: np.ndarray
    twist: np.ndarray
    started_us: np.ndarray
    next_search_us: np.ndarray
    retry_in_us: np.ndarray
    start_pending: np.ndarray
    next_check_us: np.ndarray
    retry_us: int
    start_after_us: int
    check_us: int
    due: np.ndarray
    starting: np.ndarray
    checking: np.ndarray
    may: np.ndarray


@kernel
def recover_step(r, t, period_us, pose, declared, low_run, patience):
    """:func:`bookkeeping_kernel` on the :class:`RecoverArrays` ``r`` in place, for the update at times ``t`` ``(B,)``
    int64 with output poses ``pose`` ``(B, 7)``, the detector's ``declared`` (newly lost) and ``low_run`` ``(B,)`` and
    its ``patience``. Returns whether a search is due now (``r.due`` or ``r.starting``); ``r.may[0]``: whether the
    next update may search (:meth:`Recoverer.may_search`)."""
    bookkeeping_kernel(t, period_us, pose, declared, low_run, r.lost, r.good_pose, r.good_us, r.anchor_pose,
                       r.anchor_us, r.twist, r.started_us, r.next_search_us, r.retry_in_us, r.start_pending,
                       r.retry_us, r.start_after_us, r.due, r.starting, r.next_check_us, r.check_us, r.checking)
    may = r.lost.any() or r.start_pending.any()
    for b in range(low_run.shape[0]):
        may = may or low_run[b] >= patience - 1 or (r.check_us > 0 and t[b] + period_us >= r.next_check_us[b])
    r.may[0] = may
    return r.due.any() or r.starting.any() or r.checking.any()


class Recoverer(BufferViews, nn.Module):
    """Re-localise lost elements of an :class:`~torchevtrack.tracker.EventPoseTracker` (module docstring).

    Args:
        relocalisers: one :class:`~torchevtrack.stages.relocalise.Relocaliser` per distinct mesh.
        owner: ``B`` indices into ``relocalisers``, the mesh of each element.
        retry_us: event time between two searches of a lost element (us).
        min_events: pixels of the time surface that must have fired within the last ``retry_us`` for a search.
        start_search: one search ``start_after_us`` after each (re)start.
        start_after_us: that delay (us of event time).
        check_us: event time between two depth checks of an element that is not lost (us; 0: no check).
        check_margin_px: a depth rival that costs this much less than the pose (chamfer px) flags the element drifted.

    Buffers (all with a leading ``B``):
        lost: ``(B,)`` bool, lost and not yet restarted or confirmed by a search.
        drifted: ``(B,)`` bool, the element's last depth check found a depth rival clearly cheaper than its pose.
        good_pose, good_us: ``(B, 7)`` float64 and ``(B,)`` int64, the last good pose and its time.
        twist: ``(B, 6)`` float64 ``[v, w]`` good twist (zero until measured).
        anchor_pose, anchor_us: the good pose the next twist is measured from.
        next_search_us: ``(B,)`` int64 the earliest time of a lost element's next search.
        retry_in_us: ``(B,)`` int64 the wait after its next search if that one finds nothing (doubles each time).
        started_us: ``(B,)`` int64 start of the first update's window since the last (re)start (-1: none yet).
        start_pending: ``(B,)`` bool, the start search is still to come.
        next_check_us: ``(B,)`` int64 the time of the element's next depth check.

    After each update of the tracker, :func:`recover_step` keeps the books on :meth:`arrays` (compiled, with the
    tracker's other steps) and :meth:`search` runs the depth checks and searches it finds due.
    """

    lost: torch.Tensor
    drifted: torch.Tensor
    good_pose: torch.Tensor
    good_us: torch.Tensor
    twist: torch.Tensor
    anchor_pose: torch.Tensor
    anchor_us: torch.Tensor
    next_search_us: torch.Tensor
    retry_in_us: torch.Tensor
    started_us: torch.Tensor
    start_pending: torch.Tensor

    def __init__(self, relocalisers: Sequence[Relocaliser], owner: Sequence[int], *, retry_us: int = 20_000,
                 min_events: int = 500, start_search: bool = False, start_after_us: int = 48_000, check_us: int = 0,
                 check_margin_px: float = 0.5) -> None:
        super().__init__()
        if not relocalisers or not all(isinstance(r, Relocaliser) for r in relocalisers):
            raise TypeError("relocalisers must be a non-empty list of Relocaliser")
        if not owner or any(not 0 <= int(i) < len(relocalisers) for i in owner):
            raise ValueError(f"owner must index the {len(relocalisers)} relocalisers, got {list(owner)}")
        if retry_us <= 0 or start_after_us <= 0 or min_events < 0:
            raise ValueError(f"need retry_us > 0, start_after_us > 0, min_events >= 0, got {retry_us}, "
                             f"{start_after_us}, {min_events}")
        self.relocalisers = nn.ModuleList(relocalisers)
        self.owner = [int(i) for i in owner]
        self.retry_us, self.min_events = int(retry_us), int(min_events)
        self.start_search, self.start_after_us = bool(start_search), int(start_after_us)
        if check_us < 0:
            raise ValueError(f"check_us must be >= 0 (0: no depth check), got {check_us}")
        self.check_us, self.check_margin_px = int(check_us), float(check_margin_px)
        self.checks = 0
        self.searches, self.search_s, self.restarts = 0, 0.0, 0
        B = len(self.owner)
        f64, i64 = torch.float64, torch.int64
        unit = torch.tensor([0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0], dtype=f64).expand(B, 7)
        for name in ("good_pose", "anchor_pose"):
            self.register_buffer(name, unit.clone())
        self.register_buffer("twist", torch.zeros(B, 6, dtype=f64))
        for name in ("good_us", "anchor_us", "next_search_us", "retry_in_us", "next_check_us"):
            self.register_buffer(name, torch.zeros(B, dtype=i64))
        self.register_buffer("started_us", torch.full((B,), -1, dtype=i64))
        self.register_buffer("lost", torch.zeros(B, dtype=torch.bool))
        self.register_buffer("drifted", torch.zeros(B, dtype=torch.bool))
        self.register_buffer("start_pending", torch.zeros(B, dtype=torch.bool))
        # the last update's bookkeeping (recover_step): searches due, and whether the next update may search
        self._due, self._starting, self._may = np.zeros(B, np.bool_), np.zeros(B, np.bool_), np.ones(1, np.bool_)
        self._checking = np.zeros(B, np.bool_)

    @classmethod
    def from_config(cls, cfg: RecoverConfig, camera: Camera, meshes: Sequence[trimesh.Trimesh], owner: Sequence[int],
                    radii: Sequence[float]) -> "Recoverer":
        """One relocaliser per distinct loaded mesh of ``meshes`` (the tracker's, already decimated as it renders
        them) with its bounding radius of ``radii`` (metres), :func:`search_levels` of ``cfg.search_m`` and the
        shape's :func:`~torchevtrack.mesh.symmetry_axis`, the config's clear-winner cost ``max_cost_px`` and
        :data:`SEED_COST_PX`;
        ``owner`` gives each of the ``B`` elements its mesh."""
        relocs = [Relocaliser(RasterRenderer(mesh, camera), radius, levels=search_levels(cfg.search_m),
                              max_cost_px=cfg.max_cost_px, seed_cost_px=SEED_COST_PX,
                              symmetry_axis=symmetry_axis(mesh))
                  for mesh, radius in zip(meshes, radii)]
        return cls(relocs, owner, retry_us=cfg.retry_us, min_events=cfg.min_events, start_search=cfg.start_search,
                   start_after_us=cfg.start_after_us, check_us=cfg.check_us, check_margin_px=cfg.check_margin_px)

    def reset(self, pose: torch.Tensor, mask: torch.Tensor | None = None) -> None:
        """Restart the elements of ``mask`` (default all; ``(B,)`` bool or ``(K,)`` indices) at ``pose`` ``(B, 7)``
        (other rows ignored): not lost, the good pose ``pose``, no twist, the start search (if on) to come."""
        m = batch_mask(mask, len(self.owner))
        pose = torch.as_tensor(pose, dtype=torch.float64)
        for name in ("good_pose", "anchor_pose"):
            getattr(self, name)[m] = pose[m]
        self.twist[m] = 0.0
        self.lost[m] = False
        self.drifted[m] = False
        self.started_us[m] = -1
        self.start_pending[m] = self.start_search
        k = m.numpy()
        self._due[k] = self._starting[k] = self._checking[k] = False  # (a restart within an update: nothing to search)
        self._may[0] = True

    def may_search(self) -> bool:
        """Whether the next update may search, as the last update's :func:`recover_step` found (true after a reset):
        an element is lost, the tracker's detector may declare one lost in it (its low run one update short of the
        patience), or a start search is still to come. A search reads the time surface of the events up to its
        update, so the tracker then takes no window in ahead."""
        return bool(self._may[0])

    def close(self) -> None:
        """Release the relocalisers' renderers."""
        for r in self.relocalisers:
            r.renderer.close()

    def arrays(self) -> RecoverArrays:
        """The books for compiled kernels (:func:`recover_step`): numpy views of the buffers (made again only when a
        buffer's storage changes, :class:`~torchevtrack.stages.BufferViews`) and the last update's outputs."""
        views = self.buffer_views(("lost", "good_pose", "good_us", "anchor_pose", "anchor_us", "twist", "started_us",
                                   "next_search_us", "retry_in_us", "start_pending", "next_check_us"))
        return RecoverArrays(*views, self.retry_us, self.start_after_us, self.check_us, self._due, self._starting,
                             self._checking, self._may)

    @torch.inference_mode()
    def search(self, tracker: "EventPoseTracker", t: np.ndarray) -> None:
        """Run what :func:`recover_step` found due at the update's times ``t`` ``(B,)`` int64: the depth checks (they
        set :attr:`drifted`), then the searches of the lost elements that have recent event pixels and of those whose
        start search is due; restart those whose search is clear (a start search: :func:`beats_start`)."""
        due, starting = self._due, self._starting
        B = len(self.owner)
        surface = tracker.last_event_us
        pose = tracker.pose.clone()
        restart = torch.zeros(B, dtype=torch.bool)
        found = pose.clone()
        # a start search keeps the motion the tracker measured meanwhile (the UKF's); a lost element's is not known
        twist = tracker.ukf.twist.clone() if tracker.config.ukf.enabled else torch.zeros(B, 6, dtype=torch.float64)
        twist[~torch.from_numpy(starting)] = 0.0
        for i in np.flatnonzero(self._checking).tolist():  # a depth rival clearly cheaper: drifted (reported only)
            reloc = self.relocalisers[self.owner[i]]
            if not wholly_in_view(pose[i:i + 1], reloc):
                continue
            c = reloc.rivals(pose[i:i + 1], surface[i], int(t[i]))
            self.checks += 1
            self.drifted[i] = float(c[1:].min()) < float(c[0]) - self.check_margin_px
        for i in np.flatnonzero(due | starting).tolist():
            if due[i]:
                # pixels that fired lately beside another (an edge's, not isolated noise): none in a blackout or with
                # the object out of view, and a search then waits, at no cost, for the first update that has them
                recent = recent_events(surface[i], int(t[i]), self.retry_us, min_support=1)
                if int(recent.sum()) < self.min_events:  # no edges to search in: retry later
                    continue
                dt = min(float(t[i] - self.good_us[i]), MAX_EXTRAPOLATION_US) * 1e-6
                centre = propagate(self.good_pose[i:i + 1], self.twist[i:i + 1], dt)
                self.next_search_us[i] = int(t[i]) + int(self.retry_in_us[i])
                self.retry_in_us[i] = min(2 * int(self.retry_in_us[i]), MAX_RETRY_US)
            else:
                centre = pose[i:i + 1]
            reloc = self.relocalisers[self.owner[i]]
            if not float(centre[0, 2]) > 1.5 * reloc.radius:  # extrapolated to (or behind) the camera
                centre = self.good_pose[i:i + 1]
            start = time.perf_counter()
            snapshot, t_i = surface[i:i + 1].clone(), torch.from_numpy(t[i:i + 1])
            out = reloc(centre, snapshot, t_i, pose[i:i + 1])
            self.searches += 1
            if due[i]:
                wins = found_again(out, centre, reloc)
                if not wins and not confirms(out, reloc.max_cost_px, reloc.min_margin_px) \
                        and float(out.own_cost[0]) < float(out.cost[0]):
                    # the tracker's own pose explains the events better than anything near the extrapolated one: it
                    # kept following the object while lost, so search around it
                    out = reloc(pose[i:i + 1], snapshot, t_i, pose[i:i + 1])
                    wins = found_again(out, pose[i:i + 1], reloc)
                if not wins and not confirms(out, reloc.max_cost_px, reloc.min_margin_px):
                    # not near its last pose: where in the frame is it (back in view elsewhere, or moved far)?
                    seed, _ = reloc.scan(centre, snapshot[0], int(t[i]))
                    out = reloc(seed, snapshot, t_i, pose[i:i + 1])
                    wins = found_again(out, seed, reloc)
            else:
                wins = beats_start(out, START_MARGIN_PX)
                if not wins:  # nothing clearly better by the chamfer cost: the tracker's pose turned, by the template
                    turned, score = tracker.refine(turned_poses(pose[i], TURN_DEG), i, int(t[i]))
                    k = 1 + int(score[1:].argmax())
                    if float(score[k] - score[0]) > TURN_MARGIN * abs(float(score[0])):
                        wins, out = True, out._replace(pose=turned[k:k + 1])
            self.search_s += time.perf_counter() - start
            if wins:
                restart[i] = True
                found[i] = out.pose[0]
            elif due[i] and confirms(out, reloc.max_cost_px, reloc.min_margin_px):
                self.lost[i] = False  # the tracker's own pose is as good as anything the search found
        if bool(restart.any()):
            tracker.reset(found, twist, mask=restart)  # resets this module's rows too (reset)
            self.start_pending[restart] = False  # a restart found by a search needs no start search
            self.restarts += int(restart.sum())

    def extra_repr(self) -> str:
        return (f"batch_size={len(self.owner)}, retry_us={self.retry_us}, min_events={self.min_events}, "
                f"start_search={self.start_search}, start_after_us={self.start_after_us}, check_us={self.check_us}")
