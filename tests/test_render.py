"""Renderer against analytic depth, exact pixel-centre rasterisation of projected polygons, and itself
(roi vs full frame, batch vs single)."""

import math

import numpy as np
import pytest
import torch
import trimesh

from torchevtrack.camera import Camera
from torchevtrack.geometry import quat_exp, quat_to_matrix, transform_points
from torchevtrack.mesh import load_mesh
from torchevtrack.render import BACKENDS, Render, Renderer, make_renderer

CAM = Camera(160, 120, 150.0, 140.0, 79.3, 61.7)


def pose(t, rotvec=(0.0, 0.0, 0.0)):
    q = quat_exp(torch.tensor(rotvec, dtype=torch.float64))
    return torch.cat((torch.tensor(t, dtype=torch.float64), q))


def quad(size):
    """Zero-thickness square in the object xy plane, front side (outward normal) towards -z."""
    h = size / 2
    corners = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    mesh = trimesh.Trimesh(corners, [[0, 2, 1], [0, 3, 2]], process=False)
    assert mesh.face_normals[0, 2] < 0
    return mesh, corners


def centres_inside_polygon(cam, poly):
    """Oracle: pixels whose centre lies inside a convex image polygon, and their distance to its edges."""
    uv = cam.pixel_grid(torch.float64).numpy()
    sides = []
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        e = b - a
        sides.append((e[0] * (uv[..., 1] - a[1]) - e[1] * (uv[..., 0] - a[0])) / np.linalg.norm(e))
    sides = np.stack(sides)
    if sides.sum() < 0:  # orientation of the polygon
        sides = -sides
    return (sides > 0).all(axis=0), np.abs(sides).min(axis=0)


@pytest.fixture(scope="module")
def box_renderer():
    with Renderer(load_mesh("box"), CAM) as r:
        yield r


def test_fronto_parallel_face_depth_is_analytic():
    slab = trimesh.creation.box((1.0, 1.0, 0.02))
    with Renderer(slab, CAM) as r:
        out = r.render(pose([0.0, 0.0, 0.5]))
    assert isinstance(out, Render) and out.depth.shape == (1, 120, 160) and out.depth.dtype == torch.float32
    # the slab fills the view; its front face is at z = 0.5 - 0.01 everywhere
    np.testing.assert_allclose(out.depth.numpy(), 0.49, atol=1e-4)


# Per backend: how far inside the slab's border (object frame) the depth is checked, and how closely.
# pyrender's depth buffer is 24-bit; the raster interpolates 1/z in float64.
TILTED_PLANE = {"pyrender": (0.09, dict(atol=1e-4)), "raster": (0.099, dict(rtol=1e-6))}


@pytest.mark.parametrize("backend", BACKENDS)
def test_tilted_plane_depth_and_exact_background(backend):
    slab = trimesh.creation.box((0.2, 0.2, 0.01))
    t = np.array([0.01, -0.02, 0.6])
    rotvec = (0.3, -0.5, 0.1)
    with make_renderer(slab, CAM, backend, background=0.25) as r:
        out = r.render(pose(t.tolist(), rotvec))
    R = quat_to_matrix(quat_exp(torch.tensor(rotvec, dtype=torch.float64))).numpy()
    n = R[:, 2]
    uv = CAM.pixel_grid(torch.float64).numpy()
    rays = np.stack(((uv[..., 0] - CAM.cx) / CAM.fx, (uv[..., 1] - CAM.cy) / CAM.fy, np.ones(uv.shape[:2])), -1)
    # the face seen is the one whose outward normal points to the camera (n_z > 0 here, so -n)
    assert n[2] > 0
    p0 = t - 0.005 * n
    z_plane = (n @ p0) / (rays @ n)
    # pixels whose ray hits that face well inside its border
    hits = rays * z_plane[..., None]
    local = (hits - t) @ R
    half, tol = TILTED_PLANE[backend]
    inner = (np.abs(local[..., 0]) < half) & (np.abs(local[..., 1]) < half)
    assert inner.sum() > 1000
    depth = out.depth[0].numpy()
    np.testing.assert_allclose(depth[inner], z_plane[inner], **tol)
    # far outside the slab's silhouette (object-frame distance > 0.13): exactly background
    outside = (np.abs(local[..., 0]) > 0.13) | (np.abs(local[..., 1]) > 0.13)
    assert outside.sum() > 1000
    assert (depth[outside] == 0).all()
    assert (out.gray[0].numpy()[outside] == 0.25).all()


@pytest.mark.parametrize(
    "t, rotvec",
    [
        ([0.013, 0.021, 0.45], (0.0, 0.0, 0.0)),
        ([0.031, 0.017, 0.52], (0.4, -0.3, 0.7)),
        ([-0.05, 0.02, 0.38], (-0.6, 0.2, -1.1)),
    ],
)
def test_silhouette_matches_projected_polygon(t, rotvec):
    mesh, corners = quad(0.08)
    p = pose(t, rotvec)
    with Renderer(mesh, CAM) as r:
        mask = r.render(p, shaded=False).depth[0].numpy() > 0
    poly = CAM.project(transform_points(p, torch.from_numpy(corners))).numpy()
    inside, dist = centres_inside_polygon(CAM, poly)
    # pixel-centre rasterisation: identical except for centres within 1e-3 px of an edge
    clear = dist > 1e-3
    assert (mask[clear] == inside[clear]).all()
    assert inside.sum() > 200
    # silhouette centroid vs the projection of the quad centre (fronto-parallel case: same point)
    if rotvec == (0.0, 0.0, 0.0):
        v, u = np.nonzero(mask)
        centre = CAM.project(torch.tensor(t, dtype=torch.float64)).numpy()
        assert abs(u.mean() - centre[0]) < 0.5 and abs(v.mean() - centre[1]) < 0.5


def test_vertex_marker_depth_matches_projection(box_renderer):
    # a corner of the box, seen from a pose where it is the closest point: the pixel Camera.project
    # gives for it holds the surface at (nearly) that corner's depth
    p = pose([0.02, 0.03, 0.55], (0.5, 0.6, 0.2))
    corners = torch.tensor([[sx * 0.08, sy * 0.03, sz * 0.105] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)],
                           dtype=torch.float64)
    cam_pts = transform_points(p, corners)
    near = cam_pts[cam_pts[:, 2].argmin()]
    u, v = CAM.project(near).round().long().tolist()
    depth = box_renderer.render(p, shaded=False).depth[0]
    patch = depth[v - 1 : v + 2, u - 1 : u + 2]
    assert (patch > 0).any()
    # depth grows by at most ~1 px of surface slope away from the corner itself
    assert abs(float(patch[patch > 0].min()) - float(near[2])) < 2e-3


def test_off_centre_object_lands_in_the_right_quadrant(box_renderer):
    out = box_renderer.render(pose([0.12, 0.08, 0.8], (0.2, 0.1, 0.0)), shaded=False)
    v, u = np.nonzero(out.depth[0].numpy() > 0)
    assert len(u) > 50
    # x > 0 is to the right (u > cx), y > 0 is down (v > cy) in OpenCV pixels
    assert (u > CAM.cx).all() and (v > CAM.cy).all()


def test_roi_equals_window_of_full_frame(box_renderer):
    p = pose([0.01, -0.02, 0.7], (0.3, 0.8, -0.2))
    full = box_renderer.render(p)
    u0, v0, w, h = 50, 30, 60, 55
    roi = box_renderer.render(p, roi=(u0, v0, w, h))
    assert roi.camera == CAM.crop(u0, v0, w, h) and full.camera == CAM
    assert roi.depth.shape == (1, h, w) and roi.gray.shape == (1, h, w)
    d_full = full.depth[0, v0 : v0 + h, u0 : u0 + w]
    d_roi = roi.depth[0]
    m_full, m_roi = d_full > 0, d_roi > 0
    assert m_full.sum() > 500 and m_full.sum() < m_full.numel()  # the window cuts the object
    assert int((m_full != m_roi).sum()) <= 3
    both = m_full & m_roi
    assert torch.allclose(d_roi[both], d_full[both], atol=1e-5)
    g_full = full.gray[0, v0 : v0 + h, u0 : u0 + w]
    assert float((roi.gray[0][both] - g_full[both]).abs().max()) <= 2.5 / 255
    # the full frame still renders at full size afterwards
    assert box_renderer.render(p, shaded=False).depth.shape == (1, 120, 160)


def test_roi_past_the_sensor_border(box_renderer):
    p = pose([-0.2, 0.17, 0.6])  # the box covers part of the bottom-left corner
    full = box_renderer.render(p, shaded=False).depth[0]
    roi = box_renderer.render(p, roi=(-10, 100, 40, 30), shaded=False).depth[0]
    window = full[100:, :30] > 0
    assert 0 < int(window.sum()) < window.numel()
    assert torch.equal(roi[:20, 10:] > 0, window)


@pytest.mark.parametrize(
    "t", [[0.0, 0.0, -0.5], [0.0, 0.0, -0.06], [3.0, 0.0, 0.5], [0.0, -2.0, 0.5], [0.0, 0.0, 50.0]]
)
def test_invisible_object_renders_empty(t):
    with Renderer(load_mesh("can"), CAM, background=0.4) as r:
        out = r.render(pose(t))
    assert (out.depth == 0).all()
    assert (out.gray == 0.4).all()


def test_batch_equals_individual_renders(box_renderer):
    poses = torch.stack(
        [pose([0.0, 0.0, 0.5], (0.1, 0.2, 0.3)), pose([0.05, 0.0, 0.6], (1.0, 0.0, 0.0)), pose([0.0, 0.04, 0.4])]
    )
    batch = box_renderer.render(poses)
    assert batch.depth.shape == (3, 120, 160) and batch.gray.shape == (3, 120, 160)
    for b in range(3):
        single = box_renderer.render(poses[b])
        assert torch.equal(single.depth[0], batch.depth[b])
        assert torch.equal(single.gray[0], batch.gray[b])
    # float32 poses give the same images
    assert torch.allclose(box_renderer.render(poses.float(), shaded=False).depth, batch.depth, atol=1e-5)


def test_depth_only_matches_shaded_depth(box_renderer):
    p = pose([0.0, 0.01, 0.5], (0.4, 0.3, 0.0))
    shaded = box_renderer.render(p)
    plain = box_renderer.render(p, shaded=False)
    assert plain.gray is None
    assert torch.allclose(plain.depth, shaded.depth, atol=1e-6)


@pytest.mark.parametrize(
    "rotvec", [(0.0, 0.0, 0.0), (0.0, 1.2, 0.0), (0.5, -0.4, 0.3), (-0.9, 0.2, 0.0), (1.0, -0.8, 0.0)]  # last: unlit
)
def test_grey_is_documented_lambert_model(rotvec):
    # uncoloured slab (albedo 0.75), light towards (-0.3, -0.4, -1) in the camera frame, ambient 0.3
    slab = trimesh.creation.box((0.3, 0.3, 0.01))
    with Renderer(slab, CAM, background=0.1) as r:
        out = r.render(pose([0.0, 0.0, 0.5], rotvec))
    R = quat_to_matrix(quat_exp(torch.tensor(rotvec, dtype=torch.float64))).numpy()
    n_front = -R[:, 2]  # the face towards the camera
    light = np.array([-0.3, -0.4, -1.0]) / np.linalg.norm([-0.3, -0.4, -1.0])
    expected = 0.75 * (0.3 + 0.7 * max(0.0, float(n_front @ light)))
    centre = out.gray[0, 55:66, 75:86]  # well inside the front face
    assert (out.depth[0, 55:66, 75:86] > 0).all()
    np.testing.assert_allclose(centre.numpy(), expected, atol=0.01)


def test_grey_pattern_from_vertex_colours():
    with Renderer(load_mesh("box"), CAM) as r:
        out = r.render(pose([0.0, 0.0, 0.5], (math.pi / 2, 0.0, 0.0)))  # the large +y face towards the camera
    inner = out.gray[0][out.depth[0] > 0]
    assert 0.0 <= float(inner.min()) and float(inner.max()) <= 1.0
    # the white panel (luminance ~0.93) and the red body (~0.30) on the same flat face
    assert float(inner.max() - inner.min()) > 0.4


@pytest.mark.parametrize("backend", BACKENDS)
def test_bad_inputs(backend):
    mesh = load_mesh("can")
    make = lambda *a, **k: make_renderer(*a, backend=backend, **k)  # noqa: E731
    with pytest.raises(TypeError, match="mesh"):
        make("can", CAM)
    with pytest.raises(TypeError, match="camera"):
        make(mesh, (160, 120))
    with pytest.raises(ValueError, match="znear"):
        make(mesh, CAM, znear=0.0)
    with pytest.raises(ValueError, match="no faces"):
        make(trimesh.Trimesh(), CAM)
    with pytest.raises(ValueError, match="background"):
        make(mesh, CAM, background=math.nan)
    r = make(mesh, CAM)
    with pytest.raises(ValueError, match=r"\(B, 7\)"):
        r.render(torch.zeros(2, 6))
    with pytest.raises(ValueError, match="unit norm"):
        r.render(torch.tensor([0.0, 0.0, 0.5, 2.0, 0.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match="NaN"):
        r.render(torch.tensor([0.0, math.nan, 0.5, 1.0, 0.0, 0.0, 0.0]))
    with pytest.raises(TypeError, match="floating"):
        r.render(torch.tensor([0, 0, 1, 1, 0, 0, 0]))
    with pytest.raises(ValueError, match="roi"):
        r.render(pose([0.0, 0.0, 0.5]), roi=(0, 0, 0, 10))
    with pytest.raises(ValueError, match="roi"):
        r.render(pose([0.0, 0.0, 0.5]), roi=(0.5, 0, 10, 10))
    r.close()
    with pytest.raises(RuntimeError, match="closed"):
        r.render(pose([0.0, 0.0, 0.5]))


def test_closing_or_dropping_one_renderer_keeps_the_others_working(box_renderer):
    p = pose([0.0, 0.0, 0.5], (0.2, 0.3, 0.0))
    before = box_renderer.render(p, shaded=False).depth
    other = Renderer(load_mesh("can"), CAM)
    assert (other.render(p, shaded=False).depth > 0).any()
    other.close()
    dropped = Renderer(load_mesh("bottle"), CAM)
    dropped.render(p, shaded=False)
    del dropped  # garbage collection must not end the shared EGL display either
    assert torch.equal(box_renderer.render(p, shaded=False).depth, before)


def test_direct_drawing_equals_pyrender_forward_pass():
    # The renderer draws with pyrender's programs into its own growing framebuffer; pyrender's own render of
    # an identical scene (single-sampled, viewport = roi) is the reference, pixel for pixel.
    import pyrender

    from torchevtrack.render import _GL_FROM_CV, _pose_matrices, _pyrender_mesh, _release, _shade, _single_sampled

    mesh = load_mesh("box")
    scene = pyrender.Scene(bg_color=(0.0, 0.0, 0.0, 0.0))
    node = scene.add(_pyrender_mesh(mesh))
    cam_ref = pyrender.IntrinsicsCamera(1.0, 1.0, 0.0, 0.0, znear=0.01, zfar=20.0)
    scene.add(cam_ref, pose=_GL_FROM_CV)
    ref = pyrender.OffscreenRenderer(1, 1)
    cases = [  # small, larger, smaller and past-the-border windows, full frame; shaded and depth only
        (pose([0.0, 0.0, 0.5], (0.3, -0.2, 0.1)), (50, 30, 60, 50), True),
        (pose([0.02, -0.01, 0.45], (1.0, 0.2, 0.0)), (20, 10, 130, 100), False),
        (pose([0.0, 0.02, 0.6], (0.0, 0.7, 0.4)), (60, 40, 41, 37), True),
        (pose([0.1, 0.05, 0.5], (-0.4, 0.0, 0.9)), (100, 60, 70, 70), True),
        (pose([-0.01, 0.0, 0.4], (0.2, 0.2, 0.2)), None, True),
        (pose([0.0, 0.0, 0.55], (0.0, 0.0, 0.0)), None, False),
    ]
    try:
        with Renderer(mesh, CAM, background=0.2) as r:
            for p, roi, shaded in cases:
                out = r.render(p, roi=roi, shaded=shaded)
                cam = CAM if roi is None else CAM.crop(*roi)
                cam_ref.fx, cam_ref.fy, cam_ref.cx, cam_ref.cy = cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5
                T = _pose_matrices(p)[0]
                scene.set_pose(node, T)
                ref.viewport_width, ref.viewport_height = cam.width, cam.height
                flags = pyrender.RenderFlags.FLAT | pyrender.RenderFlags.RGBA if shaded else pyrender.RenderFlags.DEPTH_ONLY
                with _single_sampled():
                    result = ref.render(scene, flags=flags)
                depth = result[1] if shaded else result
                assert (depth > 0).any()
                np.testing.assert_array_equal(out.depth[0].numpy(), depth)
                if shaded:
                    np.testing.assert_array_equal(out.gray[0].numpy(), _shade(result[0], depth > 0, T[:3, :3], 0.2))
                else:
                    assert out.gray is None
    finally:
        _release(ref)
