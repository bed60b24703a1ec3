"""Printed textures (torchevtrack.synth.texture) and textured rendering in both backends: against a direct
bilinear/trilinear sampling oracle on a fronto-parallel quad, against each other on the built-in objects, and
against the untextured renders (inner edges of the template)."""

import math

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from torchevtrack.camera import Camera
from torchevtrack.geometry import quat_exp
from torchevtrack.mesh import load_mesh
from torchevtrack.render import AMBIENT, LIGHT_DIRECTION, Renderer
from torchevtrack.synth.texture import printed_texture

CAM = Camera(160, 120, 150.0, 140.0, 79.3, 61.7)


def pose(t, rotvec=(0.0, 0.0, 0.0)):
    q = quat_exp(torch.tensor(rotvec, dtype=torch.float64))
    return torch.cat((torch.tensor(t, dtype=torch.float64), q))


def textured_quad(size, image, uv_scale=1.0):
    """Zero-thickness square in the object xy plane facing -z (the camera at identity rotation), with
    ``uv = uv_scale * ((x + h) / 2h, (y + h) / 2h)`` at its corners."""
    h = size / 2
    corners = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    uv = uv_scale * (corners[:, :2] + h) / size
    visual = trimesh.visual.TextureVisuals(uv=uv, image=image)
    return trimesh.Trimesh(corners, [[0, 2, 1], [0, 3, 2]], visual=visual, process=False)


def bilinear(texture, u, v):
    """Oracle: GL_LINEAR sampling (repeat wrap) of a luminance image ``(H, W)`` (rows top-down, ``v`` up) at
    texture coordinates ``u, v`` (arrays), in [0, 1] units."""
    H, W = texture.shape
    x, y = u * W - 0.5, (1.0 - v) * H - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    a, b = x - x0, y - y0
    t = texture.astype(np.float64) / 255.0

    def at(i, j):
        return t[j % H, i % W]

    return ((1 - a) * (1 - b) * at(x0, y0) + a * (1 - b) * at(x0 + 1, y0) + (1 - a) * b * at(x0, y0 + 1)
            + a * b * at(x0 + 1, y0 + 1))


def frontal_shading():
    """The Lambert factor of a face whose normal points at the camera (-z in the camera frame)."""
    return AMBIENT + (1.0 - AMBIENT) * max(0.0, float(-LIGHT_DIRECTION[2]))


def stripes_image(n=64):
    """An RGB image with a known luminance: vertical bars of 5 greys and a dark diagonal band."""
    lum = np.tile(np.repeat(np.array([30, 220, 90, 250, 150], dtype=np.uint8), 13)[:n], (n, 1))
    i, j = np.indices((n, n))
    lum[np.abs(i - j) < 4] = 10
    return Image.fromarray(np.stack((lum,) * 3, axis=-1)), lum


# -- printed_texture ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["box", "can", "bottle"])
def test_printed_texture_is_valid_and_keeps_the_geometry(name):
    mesh = load_mesh(name)
    out = printed_texture(mesh, seed=7, size=256)
    assert out.visual.kind == "texture" and out.visual.material.image.size == (256, 256)
    uv = np.asarray(out.visual.uv)
    assert uv.shape == (len(out.vertices), 2) and (uv >= 0).all() and (uv <= 1).all()
    # same triangles, in the same order and winding
    np.testing.assert_array_equal(out.vertices[out.faces], mesh.vertices[mesh.faces])
    # each face maps into one grid cell (its corners were split from other directions' faces)
    cell = np.floor(np.stack((uv[:, 0], 1 - uv[:, 1]), -1) * 256 / (256 // 3)).astype(int)
    corners = cell[out.faces]
    assert (corners == corners[:, :1]).all()
    # the face's cell is its normal's dominant direction: distinct directions, distinct cells
    normal = out.face_normals
    axis = np.abs(normal).argmax(1)
    direction = 2 * axis + (normal[np.arange(len(axis)), axis] > 0)
    cell_id = corners[:, 0, 0] + 3 * corners[:, 0, 1]
    top2 = np.sort(np.abs(normal), axis=1)[:, -2:]
    clear = top2[:, 1] - top2[:, 0] > 1e-6  # faces at 45 degrees may go either way
    for d in np.unique(direction):
        assert len(np.unique(cell_id[clear & (direction == d)])) == 1
    assert len(np.unique(cell_id)) == len(np.unique(direction))


def test_printed_texture_is_deterministic_in_seed_and_contrasted():
    mesh = load_mesh("can")
    a, b, c = printed_texture(mesh, 3), printed_texture(mesh, 3), printed_texture(mesh, 4)
    ia, ib, ic = (np.asarray(m.visual.material.image) for m in (a, b, c))
    assert ia.shape == (512, 512, 3)
    np.testing.assert_array_equal(ia, ib)
    np.testing.assert_array_equal(a.visual.uv, b.visual.uv)
    assert (ia != ic).mean() > 0.1
    lum = ia @ np.array([0.299, 0.587, 0.114]) / 255
    assert np.percentile(lum, 95) - np.percentile(lum, 5) > 0.5  # printed: dark inks on light paper
    gy, gx = np.gradient(lum)
    assert (np.hypot(gx, gy) > 0.1).mean() > 0.01  # many sharp edges


def test_printed_texture_bad_inputs():
    with pytest.raises(TypeError, match="trimesh"):
        printed_texture(np.zeros((3, 3)), 0)
    with pytest.raises(ValueError, match="size"):
        printed_texture(load_mesh("box"), 0, size=16)


# -- pyrender backend ---------------------------------------------------------------------------------------------
def test_pyrender_samples_the_texture_bilinearly_when_magnified():
    image, lum = stripes_image()
    mesh = textured_quad(0.2, image)
    with Renderer(mesh, CAM, background=0.1) as r:
        out = r.render(pose([0.0, 0.0, 0.25]))  # 0.2 m at 0.25 m: ~120 px for 64 texels (magnified)
    depth, gray = out.depth[0].numpy(), out.gray[0].numpy()
    v_px, u_px = np.indices(depth.shape)
    X = (u_px - CAM.cx) * 0.25 / CAM.fx
    Y = (v_px - CAM.cy) * 0.25 / CAM.fy
    u, v = (X + 0.1) / 0.2, (Y + 0.1) / 0.2
    inside = (u > 0.01) & (u < 0.99) & (v > 0.01) & (v < 0.99)
    assert (depth[inside] > 0).all() and inside.sum() > 5000
    expected = bilinear(lum, u, v) * frontal_shading()
    err = np.abs(gray - expected)[inside]
    assert err.mean() < 3e-3 and np.percentile(err, 99) < 0.012
    assert gray[inside].std() > 0.2  # the texture's bars are there


def test_face_colours_give_each_face_its_albedo():
    slab = trimesh.creation.box((0.3, 0.3, 0.01))
    colours = np.tile(np.array([200, 200, 200, 255], dtype=np.uint8), (len(slab.faces), 1))
    front = slab.face_normals[:, 2] < -0.5
    colours[np.flatnonzero(front)[0]] = (20, 40, 200, 255)  # one triangle of the front face: dark blue
    slab.visual.face_colors = colours
    with Renderer(slab, CAM) as r:
        gray = r.render(pose([0.0, 0.0, 0.5])).gray[0].numpy()
    lum = np.array([(20 * 0.299 + 40 * 0.587 + 200 * 0.114) / 255, 200 / 255])
    values = gray[40:80, 60:100].ravel()
    near = np.abs(values[:, None] - lum[None] * frontal_shading()).min(1)
    assert np.percentile(near, 90) < 0.01  # each pixel is one face's albedo (not blended across the face)
    assert (np.abs(values - lum[0] * frontal_shading()) < 0.01).mean() > 0.2
    assert (np.abs(values - lum[1] * frontal_shading()) < 0.01).mean() > 0.2


def test_textured_render_has_inner_edges_where_the_untextured_is_smooth():
    box = load_mesh("box")
    mesh = trimesh.Trimesh(box.vertices, box.faces, process=False)  # uncoloured: shading alone
    p = pose([0.0, 0.0, 0.5], (0.4, 0.5, 0.1))
    with Renderer(printed_texture(mesh, 2), CAM) as a, Renderer(mesh, CAM) as b:
        ta, tb = a.render(p), b.render(p)
    np.testing.assert_array_equal(ta.depth.numpy(), tb.depth.numpy())  # same geometry, same silhouette
    grad = [np.hypot(*np.gradient(t.gray[0].numpy())) for t in (ta, tb)]
    inner = _eroded(tb.depth[0].numpy() > 0, 2)
    assert grad[0][inner].mean() > 3 * grad[1][inner].mean()


def _eroded(mask, n):
    from scipy import ndimage

    return ndimage.binary_erosion(mask, np.ones((2 * n + 1, 2 * n + 1)))
