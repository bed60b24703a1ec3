"""RasterRenderer against pyrender (the independent oracle: OpenGL's rasteriser), against analytic depth,
shading and perspective-correct interpolation, and against its own rules (ties on edges, near and far planes,
roi vs full frame, batch vs single, bad inputs)."""

import math

import numpy as np
import pytest
import torch
import trimesh
from scipy import ndimage

from torchevtrack.camera import Camera
from torchevtrack.config import TrackerConfig
from torchevtrack.geometry import quat_exp, quat_to_matrix
from torchevtrack.mesh import load_mesh
from torchevtrack.raster import RasterRenderer
from torchevtrack.render import Render, Renderer, make_renderer
from torchevtrack.tracker import EventPoseTracker

CAM = Camera(160, 120, 150.0, 140.0, 79.3, 61.7)
FULL = Camera.default()  # 640x480, the tracker's camera

# pyrender stores albedo and the normal in 8-bit colour channels: albedo is off by up to 0.5 / 255 and each
# normal component by up to 1 / 255, which moves n . l / |n| by up to sqrt(3) / 255 / 0.95 (|n| >= 0.95 for
# normals interpolated within 30 degrees); grey = albedo (0.3 + 0.7 cos) then differs by up to
# 0.5 / 255 + 0.7 * sqrt(3) / 255 / 0.95 = 0.0070 from the unquantised value; on average by ~1e-3, but up to
# ~2e-3 where a large area has one colour (the same rounding of its albedo everywhere).
GRAY_MAX, GRAY_MEAN = 0.0075, 3e-3
# OpenGL (here Mesa llvmpipe) snaps vertices to 1/256 px, so a pixel centre within ~0.004 px of an edge may go
# to the neighbouring triangle; on meshes with noisy vertex normals (YCB scans) that can change its grey by a
# few hundredths. Such pixels are rare (<= GRAY_OUTLIERS of the interior) and show a grey seen next to them.
GRAY_OUTLIERS = 1e-3


def pose(t, rotvec=(0.0, 0.0, 0.0)):
    q = quat_exp(torch.tensor(rotvec, dtype=torch.float64))
    return torch.cat((torch.tensor(t, dtype=torch.float64), q))


def compare(ref: Render, out: Render) -> dict:
    """Check a raster render against the pyrender one (per image of the batch) and return the figures.

    Silhouette (depth > 0): differs on < 1 % of the object pixels, and only on pixels next to pyrender's
    silhouette boundary (8-neighbourhood). Depth: on pixels whose 3x3 neighbourhood is object in both, at
    most 0.5 % differ by more than 1e-4 relative, and those only at depth discontinuities (the raster depth
    lies within the depths pyrender sees in the 3x3 neighbourhood). Grey: where both see the same surface
    (depth within 1e-4), within pyrender's 8-bit quantisation (``GRAY_MAX``, mean ``GRAY_MEAN``) except on
    at most ``GRAY_OUTLIERS`` of the pixels, whose raster grey lies within the range pyrender shows in the
    3x3 neighbourhood; off the object both hold the background value exactly.
    """
    assert out.depth.shape == ref.depth.shape and out.depth.dtype == torch.float32 and out.camera == ref.camera
    figures = {"object_px": 0, "silhouette_diff": 0, "depth_rel_max_same_surface": 0.0, "gray_max": 0.0}
    for b in range(ref.depth.shape[0]):
        da, db = ref.depth[b].numpy().astype(np.float64), out.depth[b].numpy().astype(np.float64)
        ma, mb = da > 0, db > 0
        n_obj = int(ma.sum())
        assert n_obj > 100
        diff = ma != mb
        boundary = ndimage.binary_dilation(ma, np.ones((3, 3))) & ~ndimage.binary_erosion(ma, np.ones((3, 3)))
        assert diff.sum() < 0.01 * n_obj and not (diff & ~boundary).any()
        inner = ndimage.binary_erosion(ma & mb, np.ones((3, 3)))
        rel = np.abs(db - da) / np.where(ma, da, 1.0)
        off = inner & (rel > 1e-4)
        assert off.sum() <= 0.005 * inner.sum()
        lo = ndimage.minimum_filter(np.where(ma, da, np.inf), 3)
        hi = ndimage.maximum_filter(da, 3)
        assert ((db[off] >= lo[off] - 1e-4) & (db[off] <= hi[off] + 1e-4)).all()
        assert (hi[off] - lo[off] > 5e-4).all()  # a discontinuity, not a smooth slope
        same = inner & (rel <= 1e-4)
        ga, gb = ref.gray[b].numpy(), out.gray[b].numpy()
        g = np.abs(gb - ga)[same]
        assert g.mean() <= GRAY_MEAN
        outlier = same & (np.abs(gb - ga) > GRAY_MAX)
        assert outlier.sum() <= GRAY_OUTLIERS * same.sum()
        lo_g, hi_g = ndimage.minimum_filter(ga, 3)[outlier], ndimage.maximum_filter(ga, 3)[outlier]
        assert ((gb[outlier] >= lo_g - GRAY_MAX) & (gb[outlier] <= hi_g + GRAY_MAX)).all()
        assert torch.equal(out.gray[b][~(ma | mb)], ref.gray[b][~(ma | mb)])
        figures["object_px"] += n_obj
        figures["silhouette_diff"] += int(diff.sum())
        figures["depth_rel_max_same_surface"] = max(figures["depth_rel_max_same_surface"], float(rel[same].max()))
        figures["gray_max"] = max(figures["gray_max"], float(g[np.abs(gb - ga)[same] <= GRAY_MAX].max()))
        figures["gray_outliers"] = figures.get("gray_outliers", 0) + int(outlier.sum())
    return figures


def render_both(mesh, camera, poses, roi=None, **kwargs):
    with Renderer(mesh, camera, **kwargs) as gl, RasterRenderer(mesh, camera, **kwargs) as cpu:
        return gl.render(poses, roi=roi), cpu.render(poses, roi=roi)


@pytest.mark.parametrize(
    "name, camera, t, rotvec, roi",
    [
        ("box", CAM, [0.01, -0.02, 0.6], (0.3, 0.8, -0.2), None),
        ("can", CAM, [0.05, 0.03, 0.4], (1.3, -0.4, 0.2), None),  # off-centre
        ("bottle", CAM, [0.0, 0.01, 0.45], (-0.6, 0.2, 2.0), (50, 20, 60, 70)),  # the window cuts the object
        ("006_mustard_bottle", FULL, [0.0, 0.0, 0.5], (0.4, -0.3, 0.1), (240, 160, 160, 160)),  # open mesh
        ("006_mustard_bottle", FULL, [0.12, -0.08, 0.7], (2.5, 0.9, -1.2), (340, 80, 150, 150)),
        ("003_cracker_box", FULL, [-0.05, 0.02, 0.6], (0.7, 2.2, 0.3), (200, 150, 180, 180)),
        ("010_potted_meat_can", FULL, [0.02, 0.04, 0.35], (-1.0, 0.5, 0.8), (220, 160, 240, 200)),
        ("002_master_chef_can", FULL, [-0.2, -0.15, 0.8], (0.2, 0.0, 0.0), (100, 20, 200, 200)),  # corner
    ],
)
def test_agrees_with_pyrender(name, camera, t, rotvec, roi):
    ref, out = render_both(load_mesh(name), camera, pose(t, rotvec), roi=roi, background=0.15)
    compare(ref, out)


def test_decimated_mesh_and_batch_agree_with_pyrender():
    mesh = load_mesh("006_mustard_bottle", decimate=4000)
    poses = torch.stack([pose([0.0, 0.0, 0.5], (0.3 * k, 0.5 - 0.2 * k, 0.1)) for k in range(4)])
    ref, out = render_both(mesh, FULL, poses, roi=(230, 150, 180, 180))
    assert out.depth.shape == (4, 180, 180) and out.gray.shape == (4, 180, 180)
    figures = compare(ref, out)
    assert figures["silhouette_diff"] <= 0.002 * figures["object_px"]


@pytest.mark.parametrize("znear, zfar", [(0.2, 20.0), (0.01, 0.2)])
def test_near_and_far_planes_clip_like_pyrender(znear, zfar):
    # the planes cut through the front faces: triangles straddling them are kept only on the visible side
    p = pose([0.0, 0.0, 0.25], (0.5, 0.7, 0.1))
    mesh = load_mesh("box")
    ref, out = render_both(mesh, CAM, p, znear=znear, zfar=zfar)
    whole = RasterRenderer(mesh, CAM).render(p, shaded=False).depth[0]
    clipped = out.depth[0][out.depth[0] > 0]
    assert (whole > 0).sum() > 1.5 * len(clipped)  # the planes removed a good part of the object
    assert clipped.min() >= znear * (1 - 1e-6) and clipped.max() <= zfar * (1 + 1e-6)
    compare(ref, out)


def test_back_faces_are_culled_like_pyrender():
    # a single square, seen from its back: both renderers show nothing; turned round, both show it
    h = 0.04
    quad = trimesh.Trimesh([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]], [[0, 2, 1], [0, 3, 2]],
                           process=False)
    for rotvec, visible in (((0.0, math.pi, 0.0), False), ((0.0, 0.3, 0.0), True)):
        ref, out = render_both(quad, CAM, pose([0.0, 0.0, 0.4], rotvec))
        assert bool((ref.depth > 0).any()) == bool((out.depth > 0).any()) == visible
        if visible:
            compare(ref, out)


@pytest.mark.parametrize("rotvec", [(0.0, 0.0, 0.0), (0.0, 1.2, 0.0), (0.5, -0.4, 0.3), (1.0, -0.8, 0.0)])  # 4th unlit
def test_grey_is_documented_lambert_model(rotvec):
    slab = trimesh.creation.box((0.3, 0.3, 0.01))  # uncoloured: albedo 0.75
    with RasterRenderer(slab, CAM, background=0.1) as r:
        out = r.render(pose([0.0, 0.0, 0.5], rotvec))
    R = quat_to_matrix(quat_exp(torch.tensor(rotvec, dtype=torch.float64))).numpy()
    light = np.array([-0.3, -0.4, -1.0]) / np.linalg.norm([-0.3, -0.4, -1.0])
    expected = 0.75 * (0.3 + 0.7 * max(0.0, float(-R[:, 2] @ light)))
    assert (out.depth[0, 55:66, 75:86] > 0).all()
    np.testing.assert_allclose(out.gray[0, 55:66, 75:86].numpy(), expected, atol=1e-6)


def test_vertex_albedo_is_interpolated_perspective_correctly():
    # a square whose albedo goes linearly from 0 (x = -h) to 1 (x = +h), turned 60 degrees about y: the grey
    # at a pixel is (x + h) / 2h of the surface point its ray hits, times the constant Lambert factor
    h = 0.05
    corners = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    colours = np.array([[0, 0, 0, 255], [255, 255, 255, 255], [255, 255, 255, 255], [0, 0, 0, 255]], dtype=np.uint8)
    quad = trimesh.Trimesh(corners, [[0, 2, 1], [0, 3, 2]], vertex_colors=colours, process=False)
    rotvec, t = (0.0, -1.05, 0.0), np.array([0.0, 0.0, 0.3])
    with RasterRenderer(quad, CAM) as r:
        out = r.render(pose(t.tolist(), rotvec))
    R = quat_to_matrix(quat_exp(torch.tensor(rotvec, dtype=torch.float64))).numpy()
    light = np.array([-0.3, -0.4, -1.0]) / np.linalg.norm([-0.3, -0.4, -1.0])
    lambert = 0.3 + 0.7 * max(0.0, float(-R[:, 2] @ light))
    uv = CAM.pixel_grid(torch.float64).numpy()
    rays = np.stack(((uv[..., 0] - CAM.cx) / CAM.fx, (uv[..., 1] - CAM.cy) / CAM.fy, np.ones(uv.shape[:2])), -1)
    n = R[:, 2]
    local = (rays * ((n @ t) / (rays @ n))[..., None] - t) @ R
    inner = (np.abs(local[..., 0]) < 0.98 * h) & (np.abs(local[..., 1]) < 0.98 * h)
    assert inner.sum() > 300 and (out.depth[0].numpy()[inner] > 0).all()
    expected = (local[..., 0] + h) / (2 * h) * lambert
    np.testing.assert_allclose(out.gray[0].numpy()[inner], expected[inner], atol=1e-5)
    # screen-space (affine) interpolation would be visibly wrong here: along the image row through the centre
    u_left, u_right = (CAM.project(torch.from_numpy(t + R @ np.array([s * h, 0.0, 0.0])))[0].item() for s in (-1, 1))
    affine = (uv[..., 0] - u_left) / (u_right - u_left) * lambert
    assert np.abs(affine - expected)[inner].max() > 0.02


def grid_plate(n: int, half: float, z: float, grey: int) -> trimesh.Trimesh:
    """A square of ``2 n^2`` faces facing the camera at depth ``z``, one vertex colour ``grey``."""
    g = np.linspace(-half, half, n + 1)
    xx, yy = np.meshgrid(g, g)
    vertices = np.stack((xx.ravel(), yy.ravel(), np.full(xx.size, z)), -1)
    k = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]).ravel()
    faces = np.concatenate((np.stack((k, k + n + 2, k + 1), -1), np.stack((k, k + n + 1, k + n + 2), -1)))
    colours = np.tile(np.array([[grey, grey, grey, 255]], dtype=np.uint8), (len(vertices), 1))
    return trimesh.Trimesh(vertices, faces, vertex_colors=colours, process=False)


def test_overdraw_keeps_the_nearest_surface_in_either_drawing_order():
    # a dark plate behind a bright one, each of thousands of faces: whichever is drawn first, every pixel shows
    # the nearest surface and its grey (the queued shading of won pixels follows the drawing order)
    far, near = grid_plate(40, 0.1, 0.05, 60), grid_plate(40, 0.05, 0.0, 220)
    p = pose([0.0, 0.0, 0.3], (0.2, -0.3, 0.1))
    renders = []
    for mesh in (trimesh.util.concatenate([far, near]), trimesh.util.concatenate([near, far]), near):
        with RasterRenderer(mesh, CAM) as r:
            renders.append(r.render(p))
    back_to_front, front_to_back, alone = renders
    assert torch.equal(back_to_front.depth, front_to_back.depth) and torch.equal(back_to_front.gray, front_to_back.gray)
    seen = alone.depth[0] > 0
    assert int(seen.sum()) > 1500 and int(((back_to_front.depth[0] > 0) & ~seen).sum()) > 1500
    assert torch.equal(back_to_front.depth[0][seen], alone.depth[0][seen])
    assert torch.equal(back_to_front.gray[0][seen], alone.gray[0][seen])


def test_pixel_centres_on_edges_are_covered_once_and_without_gaps():
    # a fronto-parallel grid whose vertices (binary fractions) project exactly onto pixel centres: every
    # diagonal and grid line passes through centres, which must all be covered (edges are inclusive and a
    # shared edge gives its two triangles exactly opposite edge values), including the outer border
    n, step = 8, 0.0625  # 8 x 8 cells of 4 px
    g = np.arange(n + 1) * step - n * step / 2
    xx, yy = np.meshgrid(g, g)
    vertices = np.stack((xx.ravel(), yy.ravel(), np.zeros(xx.size)), -1)
    k = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]).ravel()
    faces = np.concatenate((np.stack((k, k + n + 2, k + 1), -1), np.stack((k, k + n + 1, k + n + 2), -1)))
    grid = trimesh.Trimesh(vertices, faces, process=False)
    assert (grid.face_normals[:, 2] < 0).all()  # facing the camera
    cam = Camera(48, 48, 64.0, 64.0, 24.0, 24.0)
    with RasterRenderer(grid, cam) as r:
        depth = r.render(torch.tensor([0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0]), shaded=False).depth[0]
    expected = torch.zeros(48, 48)
    expected[8:41, 8:41] = 1.0  # u = 64 x + 24 for x in [-0.25, 0.25]: columns 8 .. 40 inclusive
    assert torch.equal(depth, expected)


def test_roi_equals_window_of_full_frame():
    with RasterRenderer(load_mesh("box"), CAM) as r:
        p = pose([0.01, -0.02, 0.7], (0.3, 0.8, -0.2))
        full = r.render(p)
        u0, v0, w, h = 50, 30, 60, 55
        roi = r.render(p, roi=(u0, v0, w, h))
        past = r.render(pose([-0.2, 0.17, 0.6]), roi=(-10, 100, 40, 30), shaded=False)
        corner = r.render(pose([-0.2, 0.17, 0.6]), shaded=False)
    assert roi.camera == CAM.crop(u0, v0, w, h) and roi.depth.shape == (1, h, w)
    d_full, g_full = full.depth[0, v0:v0 + h, u0:u0 + w], full.gray[0, v0:v0 + h, u0:u0 + w]
    assert 500 < int((d_full > 0).sum()) < d_full.numel()  # the window cuts the object
    assert int(((d_full > 0) != (roi.depth[0] > 0)).sum()) <= 2
    both = (d_full > 0) & (roi.depth[0] > 0)
    assert torch.allclose(roi.depth[0][both], d_full[both], rtol=1e-6)
    assert torch.allclose(roi.gray[0][both], g_full[both], atol=1e-5)
    window = corner.depth[0, 100:, :30] > 0  # the window may extend past the sensor
    assert 0 < int(window.sum()) < window.numel()
    assert torch.equal(past.depth[0, :20, 10:] > 0, window)


def test_batch_equals_individual_renders_and_depth_only_equals_shaded():
    poses = torch.stack([pose([0.0, 0.0, 0.5], (0.1, 0.2, 0.3)), pose([0.05, 0.0, 0.6], (1.0, 0.0, 0.0)),
                         pose([0.0, 0.04, 0.4])])
    with RasterRenderer(load_mesh("can"), CAM, background=0.3) as r:
        batch = r.render(poses)
        plain = r.render(poses, shaded=False)
        singles = [r.render(poses[b]) for b in range(3)]
        as_float = r.render(poses.float(), shaded=False)
    assert batch.depth.shape == (3, 120, 160) and batch.gray.shape == (3, 120, 160)
    for b in range(3):
        assert torch.equal(singles[b].depth[0], batch.depth[b]) and torch.equal(singles[b].gray[0], batch.gray[b])
    assert plain.gray is None and torch.equal(plain.depth, batch.depth)
    assert torch.allclose(as_float.depth, batch.depth, rtol=1e-5)
    assert not torch.equal(batch.depth[0], batch.depth[1])


@pytest.mark.parametrize(
    "t, roi",
    [([0.0, 0.0, -0.5], None), ([0.0, 0.0, -0.06], None), ([3.0, 0.0, 0.5], None), ([0.0, -2.0, 0.5], None),
     ([0.0, 0.0, 50.0], None), ([0.0, 0.0, 0.5], (0, 0, 30, 20)), ([0.0, 0.0, 0.5], (500, 400, 50, 50))],
)
def test_invisible_object_renders_empty(t, roi):
    with RasterRenderer(load_mesh("can"), CAM, background=0.4) as r:
        out = r.render(pose(t), roi=roi)
    assert (out.depth == 0).all() and (out.gray == 0.4).all()
    assert out.depth.shape == ((1, 120, 160) if roi is None else (1, roi[3], roi[2]))


def test_backend_factory_and_config_switch():
    mesh = load_mesh("can")
    with make_renderer(mesh, CAM, "raster", background=0.2) as r:
        assert isinstance(r, RasterRenderer) and r.background == 0.2
    with make_renderer(mesh, CAM) as r:
        assert isinstance(r, Renderer)
    with pytest.raises(ValueError, match="backend"):
        make_renderer(mesh, CAM, "opengl")
    assert TrackerConfig().render.backend == "raster"
    pyr = TrackerConfig.from_dict({"render": {"backend": "pyrender"}})
    assert pyr.render.backend == "pyrender"
    for cfg, kind in ((TrackerConfig(), RasterRenderer), (pyr, Renderer)):  # the tracker renders with it
        tracker = EventPoseTracker(CAM, mesh, cfg)
        assert all(type(r) is kind for r in tracker._renderers)
        tracker.close()
    with pytest.raises(ValueError, match="render.backend must be one of"):
        TrackerConfig.from_dict({"render": {"backend": "numba"}})
