"""CPU z-buffer rasteriser of a mesh at a batch of poses: a second backend for :mod:`torchevtrack.render`.

:class:`RasterRenderer` takes the arguments of :class:`~torchevtrack.render.Renderer` and renders the same
images (depth in metres along the optical axis, 0 off the object, and the module's Lambert grey), without
OpenGL: one compiled (numba) kernel call per render. It is the faster backend for the tracker's windows of
meshes with ~10^4 faces, where the OpenGL path (a software rasteriser on most headless machines, plus
per-call driver overhead) costs several times more.

Per pose, the kernel

1. moves every vertex into the camera frame (OpenCV axes) and projects it with the intrinsics of the
   window: pixel ``(i, j)`` of the window is the point ``(i, j)`` of the cropped camera (centres at integer
   coordinates, as :meth:`torchevtrack.camera.Camera.project` and the pyrender backend);
2. culls back faces, as pyrender does: a face is drawn only if the camera centre lies strictly in front of
   its plane (outward normal from the counter-clockwise winding); also skipped are faces with every vertex
   nearer than ``znear`` or every vertex farther than ``zfar``, and faces whose bounding box holds no
   pixel centre of the window;
3. finds the pixel centres inside each remaining face among those of its box: a centre is inside when its
   three homogeneous edge functions (2D homogeneous rasterisation, Olano and Greer 1997) are all <= 0 (the
   sign of the face's determinant). The three edge values at a pixel are its barycentric weights up to one
   common factor, so ``values / sum`` are the perspective-correct weights and the camera ``z`` of the
   surface point is ``det / sum``. Faces that cross the near plane need no clipping: their points nearer
   than ``znear`` (or farther than ``zfar``) are dropped pixel by pixel, which is what OpenGL's clipping
   leaves. A centre exactly on an edge belongs to the face, and the two faces of a shared edge compute
   exactly opposite values of it, so no centre falls between them;
4. keeps, per pixel, the face with the smallest ``z`` (z-buffer on camera ``z``, in the float32 output;
   the first face drawn wins ties);
5. shades only the visible pixels: albedo and object-frame normal are interpolated with the
   perspective-correct weights from the per-vertex attributes the pyrender backend packs
   (``torchevtrack.render.shading_mesh``), then ``gray = albedo * (AMBIENT + (1 - AMBIENT) *
   max(0, n . l) / |n|)`` with the light direction ``l`` in the object frame. A textured mesh's albedo is its
   texture's luminance at the perspective-correct UV, sampled trilinearly from mipmaps (2 x 2 means) at the level
   of detail of the pixel's footprint (exact UV derivatives), as OpenGL's ``LINEAR_MIPMAP_LINEAR``
   (:class:`RasterTexture`; about 2.3x the shaded render's time).

Steps 3-5 run on chunks of faces: the chunk's faces are set up (box, edge functions) in one loop, then
their box pixels are z-tested without branches (data-dependent branches on ~1-pixel faces cost more than
the arithmetic), queueing the pixels each face wins with its weights; the queue is shaded in order, so a
pixel won again later ends with the grey of its final face.

The geometry's arithmetic is float64; the shading's is float32, with the attributes in float32 as the pyrender
backend packs them (the grey is float32 either way; in float64 the shading cost half of the rest of a render of
mustard_fast's ~16k faces). Against the pyrender backend (which snaps vertices to 1/256 px and quantises albedo
and normal to 8 bits): silhouettes differ only on pixels whose centre lies within ~1/256 px of an edge,
depth agrees to its 24-bit depth buffer (~1e-6 relative), grey to ~1e-3 (at most ~0.007 from the 8-bit
rounding).

Example:
    >>> import torch
    >>> from torchevtrack.camera import Camera
    >>> from torchevtrack.mesh import load_mesh
    >>> from torchevtrack.raster import RasterRenderer
    >>> with RasterRenderer(load_mesh("can"), Camera(64, 48, 50.0, 50.0, 32.0, 24.0)) as r:
    ...     out = r.render(torch.tensor([0.0, 0.0, 0.3, 1.0, 0.0, 0.0, 0.0]))
    >>> out.depth.shape, round(float(out.depth[0, 24, 32]), 3)
    (torch.Size([1, 48, 64]), 0.25)
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch
import trimesh

from torchevtrack.camera import Camera
from torchevtrack.geometry import nb_quat_to_matrix
from torchevtrack.kernels import kernel
from torchevtrack.render import (
    AMBIENT,
    LIGHT_DIRECTION,
    Render,
    check_renderer_args,
    check_roi,
    shading_mesh,
    unit_poses,
)

__all__ = ["RasterMesh", "RasterRenderer", "RasterTexture", "raster_arrays", "raster_mesh", "rasterise",
           "render_kernel"]


class RasterMesh(NamedTuple):
    """The arrays the rasteriser needs of one mesh (:func:`raster_mesh`).

    Shape:
        vertices: ``(V, 3)`` float64, object frame, metres.
        faces: ``(F, 3)`` uint32 vertex indices, counter-clockwise seen from outside.
        planes: ``(4, F)`` float64: each face's outward normal (not normalised) and its offset ``n . v0``.
        albedo: ``(V,)`` float32 in ``[0, 1]``.
        normals: ``(V, 3)`` float32 unit object-frame normals.
    """

    vertices: np.ndarray
    faces: np.ndarray
    planes: np.ndarray
    albedo: np.ndarray
    normals: np.ndarray


class RasterTexture(NamedTuple):
    """The texture of a textured mesh as the rasteriser samples it (:func:`raster_arrays`): the luminance image
    and its mipmaps (2 x 2 means, rounded to 8 bits as OpenGL's), every level's rows top-down, one after another.

    Shape:
        uv: ``(V, 2)`` float32 texture coordinates of the :class:`RasterMesh` vertices (``v`` up, repeating).
        texels: ``(N,)`` float32 in ``[0, 1]``, all levels flattened.
        levels: ``(L, 3)`` int64 ``(offset into texels, width, height)`` of each level, level 0 the image.
    """

    uv: np.ndarray
    texels: np.ndarray
    levels: np.ndarray


def raster_mesh(mesh: trimesh.Trimesh) -> RasterMesh:
    """The triangles and shading attributes of the pyrender backend (crease-split vertices, albedo from the
    vertex or face colours), with the face planes used for back-face culling."""
    return raster_arrays(mesh)[0]


def raster_arrays(mesh: trimesh.Trimesh) -> tuple[RasterMesh, RasterTexture | None]:
    """:func:`raster_mesh` and, for a textured mesh (``TextureVisuals`` with UVs and an image), its
    :class:`RasterTexture` (else ``None``), from one preparation of the mesh."""
    shading = shading_mesh(mesh)
    vertices, faces = shading.vertices, shading.faces
    corners = vertices[faces]
    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    planes = np.concatenate((n, np.einsum("fk,fk->f", n, corners[:, 0])[:, None]), axis=1).T
    arrays = RasterMesh(vertices, faces.astype(np.uint32), np.ascontiguousarray(planes),
                        shading.albedo.astype(np.float32), shading.normals.astype(np.float32))
    if shading.texture is None:
        return arrays, None
    return arrays, RasterTexture(np.ascontiguousarray(shading.uv, dtype=np.float32), *_mipmaps(shading.texture))


def _mipmaps(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The ``texels`` and ``levels`` of :class:`RasterTexture` of a uint8 image ``(h, w)`` (powers of two): each
    level the 2 x 2 mean of the previous one (1-wide sides averaged in pairs along the other), down to 1 x 1."""
    level = image.astype(np.float64)
    flat, levels, offset = [], [], 0
    while True:
        h, w = level.shape
        flat.append((level / 255.0).astype(np.float32).reshape(-1))
        levels.append((offset, w, h))
        offset += w * h
        if w == 1 and h == 1:
            break
        if h > 1:
            level = (level[0::2] + level[1::2]) / 2
        if w > 1:
            level = (level[:, 0::2] + level[:, 1::2]) / 2
        level = np.floor(level + 0.5)
    return np.concatenate(flat), np.asarray(levels, dtype=np.int64)


def rasterise(mesh: RasterMesh, poses: np.ndarray, camera: Camera, *, znear: float = 0.01, zfar: float = 20.0,
              background: float = 0.0, shaded: bool = True,
              texture: RasterTexture | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Depth and Lambert grey of a mesh at each pose, seen by ``camera`` (see the module docstring); with
    ``texture`` (the mesh's, :func:`raster_arrays`) the albedo is the texture's, sampled trilinearly.

    Shape:
        poses: ``(B, 7)`` float64 ``[t (m), unit q (w, x, y, z)]``, object in the OpenCV camera frame.
        Returns depth ``(B, h, w)`` float32 metres (0 where no surface is seen) and gray ``(B, h, w)``
        float32 (``background`` where no surface is seen; ``None`` unless ``shaded``), ``(h, w)`` the
        camera size.
    """
    depth = np.empty((len(poses), camera.height, camera.width), dtype=np.float32)
    gray = np.empty_like(depth) if shaded else np.empty((len(poses), 0, 0), dtype=np.float32)
    if texture is None:
        render_kernel(*mesh, poses, camera.fx, camera.fy, camera.cx, camera.cy, znear, zfar, LIGHT_DIRECTION,
                      AMBIENT, background, depth, gray, None)
    else:
        render_kernel(*mesh, poses, camera.fx, camera.fy, camera.cx, camera.cy, znear, zfar, LIGHT_DIRECTION,
                      AMBIENT, background, depth, gray, tuple(texture))
    return depth, gray if shaded else None


_CHUNK = 256  # faces set up at a time (their records stay in the L1 cache)
_FLUSH = 2048  # pixel wins shaded at a time


@kernel
def render_kernel(vertices, faces, planes, albedo, normals, poses, fx, fy, cx, cy, znear, zfar, light, ambient,
                  background, depth, gray, texture=None):
    """:func:`rasterise` into given arrays, unchecked; releases the GIL. Rasterises pose ``b`` of ``poses`` ``(B, 7)``
    float64 (unit quaternions) into ``depth[b]`` and, unless ``gray`` has no pixels, shades it into ``gray[b]``
    (``depth``, ``gray`` ``(B, h, w)`` float32, overwritten; ``(0, 0)`` grey pixels: depth only). The mesh's
    :class:`RasterMesh` fields come first; ``fx, fy, cx, cy`` are the intrinsics of the image written (the principal
    point moved by a window's corner to render that window), ``znear, zfar`` metres, ``light``, ``ambient`` (the
    module's ``LIGHT_DIRECTION`` and ``AMBIENT``) and the grey ``background``; ``texture``: ``None`` or the tuple
    ``(uv, texels, levels)`` of the mesh's :class:`RasterTexture`."""
    B, H, W = depth.shape
    proj = np.empty(5 * vertices.shape[0])
    front, seen = np.empty(faces.shape[0], dtype=np.int64), np.empty(faces.shape[0], dtype=np.bool_)
    box, edges = np.empty((_CHUNK, 7), dtype=np.int64), np.empty((_CHUNK, 10))
    size = max(H * W, _FLUSH)  # _draw's queue never holds more
    wins, weights = np.empty((size, 2), dtype=np.int32), np.empty((size, 2), dtype=np.float32)
    for b in range(B):
        R, t = nb_quat_to_matrix(poses[b, 3], poses[b, 4], poses[b, 5], poses[b, 6]), poses[b, :3]
        _project(vertices.reshape(-1), R, t, fx, fy, cx, cy, znear, proj)
        # the camera centre in the object frame, -R^T t, and the faces it sees the front of
        c0 = -(R[0, 0] * t[0] + R[1, 0] * t[1] + R[2, 0] * t[2])
        c1 = -(R[0, 1] * t[0] + R[1, 1] * t[1] + R[2, 1] * t[2])
        c2 = -(R[0, 2] * t[0] + R[1, 2] * t[1] + R[2, 2] * t[2])
        n = _front_faces(planes[0], planes[1], planes[2], planes[3], c0, c1, c2, seen, front)
        depth[b] = 0.0
        gray[b] = background
        # n_cam . l = n_obj . (R^T l)
        light_obj = (R[0, 0] * light[0] + R[1, 0] * light[1] + R[2, 0] * light[2],
                     R[0, 1] * light[0] + R[1, 1] * light[1] + R[2, 1] * light[2],
                     R[0, 2] * light[0] + R[1, 2] * light[1] + R[2, 2] * light[2])
        shading = (albedo, normals, light_obj, ambient, gray[b].reshape(-1))
        _draw(proj, faces, front[:n], znear, zfar, depth[b], shading, box, edges, wins, weights, texture)


@kernel
def _draw(proj, faces, front, znear, zfar, depth, shading, box, edges, wins, weights, texture):
    """Z-buffer pass of the faces ``front`` over an all-zero ``depth`` ``(h, w)``: for each pixel, the camera
    ``z`` (metres) of the nearest of them in ``[znear, zfar]`` and, unless the grey image (the last of the
    ``shading`` arguments of :func:`_shade`) has no pixels, its Lambert grey. Per chunk of ``_CHUNK`` faces:
    :func:`_face_setups`, then :func:`_cover` per face, queueing the pixels won in ``wins, weights``, which
    are shaded at the end of the chunk or before ``_FLUSH`` would be passed (:func:`_shade_textured` with a
    ``texture``)."""
    H, W = depth.shape
    depth = depth.reshape(-1)
    shaded = shading[-1].size != 0
    for start in range(0, len(front), _CHUNK):
        k = _face_setups(proj, faces, front[start:start + _CHUNK], znear, zfar, W, H, box, edges)
        m = np.int64(0)
        for r in range(k):
            if m + (box[r, 1] - box[r, 0] + 1) * (box[r, 3] - box[r, 2] + 1) > _FLUSH:
                if shaded:
                    _shade_chunk(box, edges, wins[:m], weights, W, shading, texture)
                m = np.int64(0)
            m = _cover(box[r], edges[r], r, W, znear, zfar, depth, wins, weights, m)
        if shaded:
            _shade_chunk(box, edges, wins[:m], weights, W, shading, texture)


@kernel
def _front_faces(nx, ny, nz, offset, c0, c1, c2, seen, front):
    """Write into ``front`` the faces whose plane ``(nx, ny, nz) . p = offset`` has the point ``(c0, c1, c2)``
    strictly in front, in order; return their number (``seen`` is scratch)."""
    for f in range(len(seen)):
        seen[f] = nx[f] * c0 + ny[f] * c1 + nz[f] * c2 > offset[f]
    n = 0
    for f in range(len(seen)):  # branch-free compaction
        front[n] = f
        n += seen[f]
    return n


@kernel(error_model="numpy")  # no zero-division check: the loop vectorises
def _project(vertices, R, t, fx, fy, cx, cy, znear, proj):
    """Fill ``proj[5 i:5 i + 5]`` with the homogeneous image point ``(fx X + cx Z, fy Y + cy Z, Z)`` of vertex
    ``i`` (``vertices`` flattened) moved by ``R, t``, and its pixel ``(u, v)`` (NaN if nearer than ``znear``)."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = (R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0],
                                                   R[2, 1], R[2, 2])
    t0, t1, t2 = t[0], t[1], t[2]
    for i in range(len(vertices) // 3):
        px, py, pz = vertices[3 * i], vertices[3 * i + 1], vertices[3 * i + 2]
        X = r00 * px + r01 * py + r02 * pz + t0
        Y = r10 * px + r11 * py + r12 * pz + t1
        Z = r20 * px + r21 * py + r22 * pz + t2
        x, y = fx * X + cx * Z, fy * Y + cy * Z
        proj[5 * i], proj[5 * i + 1], proj[5 * i + 2] = x, y, Z
        proj[5 * i + 3] = x / Z if Z >= znear else np.nan
        proj[5 * i + 4] = y / Z if Z >= znear else np.nan


@kernel
def _cross(proj, a, b):
    """Cross product of the homogeneous points ``a`` and ``b`` of ``proj``: the edge function of the edge
    ``a -> b``, whose value at pixel ``(x, y)`` is ``result . (x, y, 1)``."""
    xa, ya, za, xb, yb, zb = proj[5 * a], proj[5 * a + 1], proj[5 * a + 2], proj[5 * b], proj[5 * b + 1], \
        proj[5 * b + 2]
    return ya * zb - za * yb, za * xb - xa * zb, xa * yb - ya * xb


@kernel
def _near_clipped_box(proj, i0, i1, i2, znear):
    """Pixel bounding box ``(umin, umax, vmin, vmax)`` of the part of a triangle at ``Z >= znear``."""
    umin = vmin = np.inf
    umax = vmax = -np.inf
    for a, b in ((i0, i1), (i1, i2), (i2, i0)):
        xa, ya, za, xb, yb, zb = proj[5 * a], proj[5 * a + 1], proj[5 * a + 2], proj[5 * b], proj[5 * b + 1], \
            proj[5 * b + 2]
        if za >= znear:  # a kept vertex
            umin, umax = min(umin, xa / za), max(umax, xa / za)
            vmin, vmax = min(vmin, ya / za), max(vmax, ya / za)
        if (za - znear) * (zb - znear) < 0.0:  # the edge crosses the near plane: there, Z = znear
            s = (znear - za) / (zb - za)
            u = (xa + s * (xb - xa)) / znear
            v = (ya + s * (yb - ya)) / znear
            umin, umax, vmin, vmax = min(umin, u), max(umax, u), min(vmin, v), max(vmax, v)
    return umin, umax, vmin, vmax


@kernel
def _face_setups(proj, faces, front, znear, zfar, W, H, box, edges):
    """Records of the faces ``front`` whose pixel box in the ``W x H`` window is not empty: ``box[r]`` their box
    ``(xmin, xmax, ymin, ymax)`` and vertex indices, ``edges[r]`` their three edge functions and ``det``
    (< 0 for a front face); returns the number of records. Skips faces wholly nearer than ``znear`` or
    farther than ``zfar`` and edge-on faces (``det >= 0`` by rounding)."""
    k = 0
    for f in front:
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        z0, z1, z2 = proj[5 * i0 + 2], proj[5 * i1 + 2], proj[5 * i2 + 2]
        if (z0 < znear and z1 < znear and z2 < znear) or (z0 > zfar and z1 > zfar and z2 > zfar):
            continue
        if z0 >= znear and z1 >= znear and z2 >= znear:
            u0, u1, u2, v0, v1, v2 = proj[5 * i0 + 3], proj[5 * i1 + 3], proj[5 * i2 + 3], proj[5 * i0 + 4], \
                proj[5 * i1 + 4], proj[5 * i2 + 4]
            umin, umax, vmin, vmax = min(u0, u1, u2), max(u0, u1, u2), min(v0, v1, v2), max(v0, v1, v2)
        else:
            umin, umax, vmin, vmax = _near_clipped_box(proj, i0, i1, i2, znear)
        xmin, xmax = max(math.ceil(umin), 0), min(math.floor(umax), W - 1)
        ymin, ymax = max(math.ceil(vmin), 0), min(math.floor(vmax), H - 1)
        e = edges[k]
        e[0], e[1], e[2] = _cross(proj, i1, i2)
        e[3], e[4], e[5] = _cross(proj, i2, i0)
        e[6], e[7], e[8] = _cross(proj, i0, i1)
        e[9] = e[0] * proj[5 * i0] + e[1] * proj[5 * i0 + 1] + e[2] * proj[5 * i0 + 2]
        box[k, 0], box[k, 1], box[k, 2], box[k, 3], box[k, 4], box[k, 5], box[k, 6] = xmin, xmax, ymin, ymax, i0, i1, i2
        k += (xmin <= xmax) & (ymin <= ymax) & (e[9] < 0.0)  # branch-free compaction
    return k


@kernel(error_model="numpy")  # 1 / 0 = inf (a sliver's z fails the range test)
def _cover(box, e, r, W, znear, zfar, depth, wins, weights, m):
    """Z-test record ``r``'s face at the pixel centres of its box against ``depth`` (the window, flattened) and
    keep it where it is nearer: there, write its ``z`` into ``depth`` and append the pixel, ``r`` and its
    first two weights at ``wins[m], weights[m]``. Returns the new ``m``. Branch-free per pixel."""
    xmin, xmax, y = box[0], box[1], box[2]
    a0, b0, c0, a1, b1, c1, a2, b2, c2, det = e[0], e[1], e[2], e[3], e[4], e[5], e[6], e[7], e[8], e[9]
    x = xmin
    for _ in range((xmax - xmin + 1) * (box[3] - y + 1)):
        e0 = a0 * x + b0 * y + c0
        e1 = a1 * x + b1 * y + c1
        e2 = a2 * x + b2 * y + c2
        inv = 1.0 / (e0 + e1 + e2)
        z = det * inv
        p = y * W + x
        d = depth[p]
        keep = (max(e0, e1, e2) <= 0.0) & (znear <= z) & (z <= zfar) & ((d == 0.0) | (z < d))
        depth[p] = np.float32(z) if keep else d
        wins[m, 0], wins[m, 1], weights[m, 0], weights[m, 1] = p, r, e0 * inv, e1 * inv
        m += keep
        x += 1
        wrap = x > xmax
        x = xmin if wrap else x
        y += wrap
    return m


@kernel
def _shade_chunk(box, edges, wins, weights, W, shading, texture):
    """:func:`_shade` the queued pixels, or :func:`_shade_textured` them with a ``texture`` (a ``None``
    texture compiles to the untextured call alone)."""
    if texture is None:
        _shade(box, wins, weights, *shading)
    else:
        _shade_textured(box, edges, wins, weights, W, texture[0], texture[1], texture[2], *shading)


@kernel
def _shade(box, wins, weights, albedo, normals, light, ambient, gray):
    """Lambert grey at the pixels ``wins[:, 0]`` of the window (``gray`` flattened), in order, from the albedo
    and normal interpolated at ``weights`` over the vertices of the records ``wins[:, 1]``, in float32 (the
    attributes and the output are float32)."""
    f4 = np.float32
    l0, l1, l2, amb = f4(light[0]), f4(light[1]), f4(light[2]), f4(ambient)
    one, tiny, zero = f4(1.0), f4(1e-6), f4(0.0)
    for j in range(wins.shape[0]):
        p, r = wins[j, 0], wins[j, 1]
        i0, i1, i2 = box[r, 4], box[r, 5], box[r, 6]
        w0, w1 = weights[j, 0], weights[j, 1]
        w2 = one - w0 - w1
        alb = w0 * albedo[i0] + w1 * albedo[i1] + w2 * albedo[i2]
        n0 = w0 * normals[i0, 0] + w1 * normals[i1, 0] + w2 * normals[i2, 0]
        n1 = w0 * normals[i0, 1] + w1 * normals[i1, 1] + w2 * normals[i2, 1]
        n2 = w0 * normals[i0, 2] + w1 * normals[i1, 2] + w2 * normals[i2, 2]
        cos = (n0 * l0 + n1 * l1 + n2 * l2) / max(math.sqrt(n0 * n0 + n1 * n1 + n2 * n2), tiny)
        gray[p] = alb * (amb + (one - amb) * max(cos, zero))


@kernel
def _shade_textured(box, edges, wins, weights, W, uv, texels, levels, albedo, normals, light, ambient, gray):
    """:func:`_shade` with the albedo sampled from the texture (``texels, levels`` of :class:`RasterTexture`) at
    the perspective-correct ``uv``, trilinearly as OpenGL's ``LINEAR_MIPMAP_LINEAR`` (repeating): the level of
    detail is ``log2`` of the larger pixel footprint in texels, from the exact derivatives of ``uv`` along the
    window's x and y (``uv = sum e_i uv_i / sum e_i`` with the face's edge functions ``e_i``)."""
    f4 = np.float32
    l0, l1, l2, amb = f4(light[0]), f4(light[1]), f4(light[2]), f4(ambient)
    one, tiny, zero = f4(1.0), f4(1e-6), f4(0.0)
    W0, H0, top = levels[0, 1], levels[0, 2], levels.shape[0] - 1
    for j in range(wins.shape[0]):
        p, r = wins[j, 0], wins[j, 1]
        i0, i1, i2 = box[r, 4], box[r, 5], box[r, 6]
        w0, w1 = weights[j, 0], weights[j, 1]
        w2 = one - w0 - w1
        u = w0 * uv[i0, 0] + w1 * uv[i1, 0] + w2 * uv[i2, 0]
        v = w0 * uv[i0, 1] + w1 * uv[i1, 1] + w2 * uv[i2, 1]
        # d(uv)/dx = (sum a_i uv_i - uv sum a_i) / S, S = sum e_i at the pixel (the same for y with b_i)
        e = edges[r]
        x, y = p % W, p // W
        a, b = e[0] + e[3] + e[6], e[1] + e[4] + e[7]
        S = a * x + b * y + e[2] + e[5] + e[8]
        dudx = (e[0] * uv[i0, 0] + e[3] * uv[i1, 0] + e[6] * uv[i2, 0] - u * a) / S
        dvdx = (e[0] * uv[i0, 1] + e[3] * uv[i1, 1] + e[6] * uv[i2, 1] - v * a) / S
        dudy = (e[1] * uv[i0, 0] + e[4] * uv[i1, 0] + e[7] * uv[i2, 0] - u * b) / S
        dvdy = (e[1] * uv[i0, 1] + e[4] * uv[i1, 1] + e[7] * uv[i2, 1] - v * b) / S
        rho2 = max((dudx * W0) ** 2 + (dvdx * H0) ** 2, (dudy * W0) ** 2 + (dvdy * H0) ** 2)
        lod = 0.5 * math.log2(rho2) if rho2 > 1.0 else 0.0
        lo = min(int(lod), top)
        t = lod - lo if lo < top else 0.0
        alb = _bilinear(texels, levels[lo], u, v)
        if t > 0.0:
            alb = (1.0 - t) * alb + t * _bilinear(texels, levels[lo + 1], u, v)
        n0 = w0 * normals[i0, 0] + w1 * normals[i1, 0] + w2 * normals[i2, 0]
        n1 = w0 * normals[i0, 1] + w1 * normals[i1, 1] + w2 * normals[i2, 1]
        n2 = w0 * normals[i0, 2] + w1 * normals[i1, 2] + w2 * normals[i2, 2]
        cos = (n0 * l0 + n1 * l1 + n2 * l2) / max(math.sqrt(n0 * n0 + n1 * n1 + n2 * n2), tiny)
        gray[p] = f4(alb) * (amb + (one - amb) * max(cos, zero))


@kernel
def _bilinear(texels, level, u, v):
    """Bilinear sample (repeating) of one mipmap ``level`` ``(offset, width, height)`` at ``(u, v)`` (``v`` up;
    texel centres at half-integers, as OpenGL's)."""
    offset, w, h = level[0], level[1], level[2]
    x, y = u * w - 0.5, (1.0 - v) * h - 0.5
    fx, fy = math.floor(x), math.floor(y)
    ax, ay = x - fx, y - fy
    c0, r0 = int(fx), int(fy)
    if 0 <= c0 < w - 1:  # inside: no wrap (an integer modulo per texel is most of a sample's cost)
        c1 = c0 + 1
    else:
        c0 %= w
        c1 = (c0 + 1) % w
    if 0 <= r0 < h - 1:
        r1 = r0 + 1
    else:
        r0 %= h
        r1 = (r0 + 1) % h
    top = (1.0 - ax) * texels[offset + r0 * w + c0] + ax * texels[offset + r0 * w + c1]
    bottom = (1.0 - ax) * texels[offset + r1 * w + c0] + ax * texels[offset + r1 * w + c1]
    return (1.0 - ay) * top + ay * bottom


class RasterRenderer:
    """CPU renderer of one mesh seen by one camera, a drop-in for :class:`~torchevtrack.render.Renderer`.

    Args:
        mesh: the object (metres, outward-facing winding: back faces are culled); its vertex
            colours give the albedo (luminance), uncoloured meshes get ``DEFAULT_ALBEDO``.
        camera: the full-frame camera.
        znear, zfar: clipping distances in metres (``0 < znear < zfar``).
        background: grey value of pixels where no surface is seen.

    The mesh's triangles and shading attributes are prepared once here; :meth:`close` and the context
    manager exist for parity with the OpenGL renderer (they free those arrays).
    """

    def __init__(
        self,
        mesh: trimesh.Trimesh,
        camera: Camera,
        *,
        znear: float = 0.01,
        zfar: float = 20.0,
        background: float = 0.0,
    ) -> None:
        check_renderer_args(mesh, camera, znear, zfar, background)
        self.camera = camera
        self.znear, self.zfar = float(znear), float(zfar)
        self.background = float(background)
        self._mesh: RasterMesh | None
        self._texture: RasterTexture | None
        self._mesh, self._texture = raster_arrays(mesh)

    def close(self) -> None:
        """Drop the mesh and its texture (the renderer can no longer be used)."""
        self._mesh = self._texture = None

    @property
    def raster_mesh(self) -> RasterMesh:
        """The mesh's arrays the kernel draws (:func:`raster_mesh`)."""
        if self._mesh is None:
            raise RuntimeError("renderer is closed")
        return self._mesh

    @property
    def raster_texture(self) -> RasterTexture | None:
        """The mesh's texture as the kernel samples it, ``None`` for an untextured mesh (:func:`raster_arrays`)."""
        if self._mesh is None:
            raise RuntimeError("renderer is closed")
        return self._texture

    def __enter__(self) -> "RasterRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def render(
        self,
        poses: torch.Tensor,
        *,
        roi: tuple[int, int, int, int] | None = None,
        shaded: bool = True,
    ) -> Render:
        """Render the mesh at each pose: the arguments, result and errors of
        :meth:`torchevtrack.render.Renderer.render` (poses ``(B, 7)`` or ``(7,)``, an optional ``roi`` window,
        ``shaded=False`` for depth only)."""
        if self._mesh is None:
            raise RuntimeError("renderer is closed")
        cam = self.camera if roi is None else self.camera.crop(*check_roi(roi))
        depth, gray = self.render_unit(unit_poses(poses), cam, shaded)
        return Render(depth=torch.from_numpy(depth), gray=None if gray is None else torch.from_numpy(gray), camera=cam)

    def render_unit(self, poses: np.ndarray, camera: Camera,
                    shaded: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """:meth:`render` unchecked, in numpy: unit poses ``(B, 7)`` float64, ``camera`` this renderer's camera or a
        crop of it; returns depth and grey (or ``None``) ``(B, h, w)`` float32 (for a caller whose poses are valid,
        such as the tracker)."""
        return rasterise(self._mesh, poses, camera, znear=self.znear, zfar=self.zfar, background=self.background,
                         shaded=shaded, texture=self._texture)
