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
from torchevtrack.raster import RasterRenderer
from torchevtrack.render import AMBIENT, BACKENDS, LIGHT_DIRECTION, Renderer, make_renderer
from torchevtrack.stages import template as tm
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
    """Oracle: GL_LINEAR sampling (repeat wrap) of an image ``(H, W)`` (rows top-down, ``v`` up) at texture
    coordinates ``u, v`` (arrays)."""
    H, W = texture.shape
    x, y = u * W - 0.5, (1.0 - v) * H - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    a, b = x - x0, y - y0
    t = np.asarray(texture, dtype=np.float64)

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


@pytest.mark.parametrize("size", [48, 64, 100, 128])
def test_printed_texture_small_images(size):
    """Every size from the documented 48 px draws (marks narrower than a pixel are one pixel wide), ink on paper."""
    for seed in range(10):
        image = np.asarray(printed_texture(load_mesh("box"), seed, size=size).visual.material.image)
        assert image.shape == (size, size, 3) and np.ptp(image @ np.array([0.299, 0.587, 0.114])) > 100


def test_printed_texture_bad_inputs():
    with pytest.raises(TypeError, match="trimesh"):
        printed_texture(np.zeros((3, 3)), 0)
    with pytest.raises(ValueError, match="size"):
        printed_texture(load_mesh("box"), 0, size=16)


# -- both backends ------------------------------------------------------------------------------------------------
def trilinear(lum, u, v, lod):
    """Oracle: GL_LINEAR_MIPMAP_LINEAR sampling at a level of detail ``lod`` (scalar), mipmaps by 2 x 2 means."""
    levels = [lum.astype(np.float64)]
    while levels[-1].shape[0] > 1:
        a = levels[-1]
        levels.append((a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2]) / 4)
    if lod <= 0:
        return bilinear(levels[0], u, v)
    lo = int(math.floor(lod))
    t = lod - lo
    return (1 - t) * bilinear(levels[lo], u, v) + t * bilinear(levels[lo + 1], u, v)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("uv_scale", [1.0, 7.5])  # magnified ~2x; minified ~4x (repeating 7.5 times)
def test_texture_is_sampled_as_opengl_does(backend, uv_scale):
    image, lum = stripes_image()
    mesh = textured_quad(0.2, image, uv_scale)
    z = 0.25
    with make_renderer(mesh, CAM, backend, background=0.1) as r:
        out = r.render(pose([0.0, 0.0, z]))
    depth, gray = out.depth[0].numpy(), out.gray[0].numpy()
    v_px, u_px = np.indices(depth.shape)
    X = (u_px - CAM.cx) * z / CAM.fx
    Y = (v_px - CAM.cy) * z / CAM.fy
    u, v = (X + 0.1) / 0.2, (Y + 0.1) / 0.2
    inside = (u > 0.01) & (u < 0.99) & (v > 0.01) & (v < 0.99)
    assert (depth[inside] > 0).all() and inside.sum() > 5000
    # the footprint of a pixel in texels (uv is affine in the pixel on a fronto-parallel quad)
    rho = max(z / (CAM.fx * 0.2), z / (CAM.fy * 0.2)) * uv_scale * lum.shape[0]
    expected = trilinear(lum / 255.0, u * uv_scale, v * uv_scale, math.log2(rho)) * frontal_shading()
    err = np.abs(gray - expected)[inside]
    assert err.mean() < 4e-3 and np.percentile(err, 99) < 0.015
    assert gray[inside].std() > 0.05  # the texture's bars are there


def test_textured_renders_of_both_backends_agree():
    cam = Camera(320, 240, 300.0, 300.0, 159.5, 119.5)
    for name, z in [("box", 0.35), ("can", 0.8), ("bottle", 0.5)]:
        mesh = printed_texture(load_mesh(name), 11)
        p = pose([0.01, -0.01, z], (0.5, 0.6, 0.2))
        with Renderer(mesh, cam, background=0.2) as a, RasterRenderer(mesh, cam, background=0.2) as b:
            ra, rb = a.render(p), b.render(p)
        ma, mb = ra.depth[0].numpy() > 0, rb.depth[0].numpy() > 0
        assert (ma != mb).sum() <= 0.002 * ma.sum()
        inner = _eroded(ma & mb, 1)
        ga, gb = ra.gray[0].numpy(), rb.gray[0].numpy()
        err = np.abs(ga - gb)[inner]
        assert err.mean() < 4e-3 and np.percentile(err, 99) < 0.03
        assert np.hypot(*np.gradient(gb))[inner].mean() > 0.02  # and the texture is there


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


@pytest.mark.parametrize("backend", BACKENDS)
def test_textured_render_has_inner_edges_where_the_untextured_is_smooth(backend):
    box = load_mesh("box")
    mesh = trimesh.Trimesh(box.vertices, box.faces, process=False)  # uncoloured: shading alone
    p = pose([0.0, 0.0, 0.5], (0.4, 0.5, 0.1))
    with make_renderer(printed_texture(mesh, 2), CAM, backend) as a, make_renderer(mesh, CAM, backend) as b:
        ta, tb = a.render(p), b.render(p)
    np.testing.assert_array_equal(ta.depth.numpy(), tb.depth.numpy())  # same geometry, same silhouette
    grad = [np.hypot(*np.gradient(t.gray[0].numpy())) for t in (ta, tb)]
    inner = _eroded(tb.depth[0].numpy() > 0, 2)
    assert grad[0][inner].mean() > 3 * grad[1][inner].mean()


def _eroded(mask, n):
    from scipy import ndimage

    return ndimage.binary_erosion(mask, np.ones((2 * n + 1, 2 * n + 1)))


@pytest.mark.parametrize("name", ["box", "bottle"])
def test_template_of_a_textured_mesh_has_inner_edges(name):
    """The tracker's template (Sobel + DoG of the raster render) inside the silhouette: several times the edge
    energy of the same geometry untextured (whose only inner edges are shading creases)."""
    geometry = load_mesh(name)
    plain = trimesh.Trimesh(geometry.vertices, geometry.faces, process=False)
    cam = Camera(320, 240, 300.0, 300.0, 159.5, 119.5)
    p = pose([0.0, 0.0, 0.45], (0.4, 0.5, 0.1))[None]
    energy = []
    for mesh in (printed_texture(plain, 4), plain):
        with RasterRenderer(mesh, cam, background=0.2) as r:
            out = r.render(p)
        model = tm.template_model(p, out.depth, out.gray, (0, 0), cam)
        mask = tm.to_canvas((out.depth > 0).to(out.depth.dtype), model.box, 128)[0].numpy() > 0.999
        inner = _eroded(mask, 10)  # away from the silhouette's band
        assert inner.sum() > 500
        energy.append(float(np.abs(model.render_template[0].numpy())[inner].mean()))
    assert energy[0] > 4 * energy[1]
