"""Headless depth and shaded-grey rendering of a mesh at a batch of poses (pyrender, offscreen).

pyrender (the ``gl`` extra) is imported when the first :class:`Renderer` is made, after choosing the
OpenGL platform: ``PYOPENGL_PLATFORM`` if set, else EGL when ``libEGL`` is present, else OSMesa. The
scene (mesh and camera) is built once; each render only moves the mesh node and, for a region of
interest, changes the intrinsics and the viewport size.

Shading is a Lambert model with a light fixed to the camera, evaluated per pixel in numpy: one
unlit (flat) RGBA pass rasterises each surface point's albedo and its interpolated object-frame
normal (vertex attributes packed in the colour channels), then

    gray = albedo * (AMBIENT + (1 - AMBIENT) * max(0, n_cam . l)),

with ``AMBIENT = 0.3`` and ``l`` the unit direction towards the light, ``(-0.3, -0.4, -1)``
normalised in the OpenCV camera frame (the light sits up-left of the lens). ``albedo`` is the
luminance (0.299 R + 0.587 G + 0.114 B) of the mesh's texture (a trimesh ``TextureVisuals`` with UVs and an
image, sampled trilinearly with mipmaps and repeating UVs, as OpenGL's ``LINEAR_MIPMAP_LINEAR``), else of its
face or vertex colours, 0.75 for uncoloured meshes.
This is several times cheaper than pyrender's PBR shader on a software rasteriser. Depth and grey
are point samples at pixel centres (no anti-aliasing); render a scaled camera and pool for smoother
edges.

One offscreen context is kept per renderer: pyrender binds a mesh's GPU buffers to a single
context. pyrender compiles the shader programs and uploads the mesh; each render then draws with those
programs directly into one framebuffer that only grows (pyrender's own forward pass traverses the scene,
looks up every uniform and recreates its framebuffers whenever the viewport size changes; the pixels are
the same).

A second backend with the same interface and images, a compiled CPU z-buffer without OpenGL, is
:class:`torchevtrack.raster.RasterRenderer`; :func:`make_renderer` builds either.

Conventions: poses are ``[tx, ty, tz, qw, qx, qy, qz]`` (object in the OpenCV camera frame, metres);
pixel ``(u, v)`` centres are at integer coordinates, so a point projected by
:meth:`torchevtrack.camera.Camera.project` to ``(u, v)`` lands in pixel ``(round(u), round(v))``.

Example:
    >>> import torch
    >>> from torchevtrack.camera import Camera
    >>> from torchevtrack.mesh import load_mesh
    >>> from torchevtrack.render import Renderer
    >>> with Renderer(load_mesh("can"), Camera(64, 48, 50.0, 50.0, 32.0, 24.0)) as r:
    ...     out = r.render(torch.tensor([0.0, 0.0, 0.3, 1.0, 0.0, 0.0, 0.0]))
    >>> out.depth.shape, round(float(out.depth[0, 24, 32]), 3)
    (torch.Size([1, 48, 64]), 0.25)
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import math
import os
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
import trimesh
from PIL import Image

from torchevtrack.camera import Camera
from torchevtrack.geometry import nb_normalise_quaternions, pose_to_matrix

__all__ = ["AMBIENT", "BACKENDS", "DEFAULT_ALBEDO", "LIGHT_DIRECTION", "Render", "Renderer", "ShadingMesh",
           "check_renderer_args", "check_roi", "make_renderer", "shading_mesh", "unit_poses"]

# Camera node pose: the OpenGL camera frame (x right, y up, z backwards) seen from the OpenCV frame.
_GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])
_LUMA = np.array([0.299, 0.587, 0.114])
AMBIENT = 0.3
# unit vector towards the light in the OpenCV camera frame: up-left of the lens, mostly frontal
LIGHT_DIRECTION = np.array([-0.3, -0.4, -1.0]) / np.linalg.norm([-0.3, -0.4, -1.0])
DEFAULT_ALBEDO = 0.75
_CREASE_ANGLE = math.radians(30.0)
BACKENDS = ("pyrender", "raster")  # make_renderer's choices: this module's Renderer, torchevtrack.raster.RasterRenderer


def _select_gl_platform() -> None:
    """Pick the PyOpenGL platform before anything imports OpenGL (an explicit setting wins)."""
    if "PYOPENGL_PLATFORM" in os.environ:
        return
    if ctypes.util.find_library("EGL") is None and ctypes.util.find_library("OSMesa") is not None:
        os.environ["PYOPENGL_PLATFORM"] = "osmesa"
    else:
        os.environ["PYOPENGL_PLATFORM"] = "egl"


pyrender = GL = _STORAGE_MULTISAMPLE = None  # bound by _load_gl, when the first Renderer is made


def _load_gl() -> None:
    """Import pyrender and OpenGL (the ``gl`` extra) once, after choosing the platform.

    PyOpenGL reads ``PYOPENGL_PLATFORM`` when it is first imported, so :func:`_select_gl_platform` sets it
    here, when a :class:`Renderer` is made; importing this module (or ``torchevtrack``) loads no OpenGL and
    sets no environment variable. Raises ``ImportError`` with the install command if pyrender is missing.
    """
    global pyrender, GL, _STORAGE_MULTISAMPLE
    if pyrender is not None:
        return
    _select_gl_platform()
    try:
        import pyrender.renderer
        from OpenGL import GL
    except ImportError as e:
        raise ImportError(f"the OpenGL renderer needs pyrender ({e}): pip install 'torchevtrack[gl]', "
                          "or use the built-in renderer (render backend 'raster')") from e
    _STORAGE_MULTISAMPLE = pyrender.renderer.glRenderbufferStorageMultisample


def _single_sample_storage(target, samples, internalformat, width, height):
    return _STORAGE_MULTISAMPLE(target, 0, internalformat, width, height)


@contextlib.contextmanager
def _single_sampled():
    """Make pyrender allocate its framebuffers without multisampling while we render.

    pyrender draws into 4x multisample buffers and resolves depth by keeping one sample, which lies
    off the pixel centre (a ~0.4 px shift of depth and silhouettes). With single-sample buffers the
    depth and the grey image are both point samples at pixel centres, as the camera model assumes.
    Only the allocation call is swapped, and only for the duration of our own render calls.
    """
    pyrender.renderer.glRenderbufferStorageMultisample = _single_sample_storage
    try:
        yield
    finally:
        pyrender.renderer.glRenderbufferStorageMultisample = _STORAGE_MULTISAMPLE




@dataclass
class Render:
    """Result of :meth:`Renderer.render`.

    Attributes:
        depth: ``(B, h, w)`` float32, metres along the optical axis, 0 where no surface is seen.
        gray: ``(B, h, w)`` float32 in ``[0, 1]``, shaded luminance (``None`` if ``shaded=False``);
            background pixels hold the renderer's ``background`` value.
        camera: the camera of these images (the cropped intrinsics when an roi was given).
    """

    depth: torch.Tensor
    gray: torch.Tensor | None
    camera: Camera


class Renderer:
    """Offscreen renderer of one mesh seen by one camera.

    Args:
        mesh: the object (metres, outward-facing winding: back faces are culled); its vertex
            colours give the albedo (luminance), uncoloured meshes get ``DEFAULT_ALBEDO``.
        camera: the full-frame camera.
        znear, zfar: clipping distances in metres (``0 < znear < zfar``).
        background: grey value of pixels where no surface is seen.

    Shading: the module's Lambert model (light fixed to the camera, so the grey of a face changes
    as the object rotates); normals are smoothed except across creases sharper than 30 degrees.
    Use as a context manager or call :meth:`close` to free the GL context.
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
        _load_gl()
        self.camera = camera
        self.background = float(background)

        self._scene = pyrender.Scene(bg_color=(0.0, 0.0, 0.0, 0.0))
        self._mesh_node = self._scene.add(_pyrender_mesh(mesh))
        self._cam = pyrender.IntrinsicsCamera(
            camera.fx, camera.fy, camera.cx + 0.5, camera.cy + 0.5, znear=float(znear), zfar=float(zfar)
        )
        self._scene.add(self._cam, pose=_GL_FROM_CV)
        self._offscreen: pyrender.OffscreenRenderer | None = None
        self._target: _GLTarget | None = None

    # -- context management ----------------------------------------------------------------------
    def _gl(self, width: int, height: int) -> "_GLTarget":
        """The current GL context with this renderer's programs and a framebuffer of at least ``width x height``."""
        if self._offscreen is None:
            try:
                self._offscreen = pyrender.OffscreenRenderer(1, 1)
            except Exception as e:
                platform = os.environ.get("PYOPENGL_PLATFORM")
                raise RuntimeError(
                    f"cannot create an offscreen OpenGL context with PYOPENGL_PLATFORM={platform} "
                    f"({type(e).__name__}: {e}). EGL needs libEGL (Mesa, e.g. Debian libegl1 + libgl1-mesa-dri); "
                    "OSMesa needs libosmesa6 and PyOpenGL>=3.1.10. Set PYOPENGL_PLATFORM before importing "
                    "torchevtrack.render."
                ) from e
            self._target = _GLTarget(self._offscreen, self._scene, self._mesh_node)
        self._offscreen._platform.make_current()
        self._target.reserve(width, height)
        return self._target

    def close(self) -> None:
        """Free the OpenGL context (the renderer can no longer be used)."""
        if self._offscreen is not None:
            self._offscreen._platform.make_current()
            self._target.delete()
            _release(self._offscreen)
            self._offscreen = None
            self._target = None
        self._scene = None

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown: GL libraries may already be gone
            pass

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- rendering -------------------------------------------------------------------------------
    def render(
        self,
        poses: torch.Tensor,
        *,
        roi: tuple[int, int, int, int] | None = None,
        shaded: bool = True,
    ) -> Render:
        """Render the mesh at each pose.

        Args:
            poses: ``(B, 7)`` or ``(7,)`` object-in-camera poses ``[t (m), q (w, x, y, z)]``. Poses
                behind the camera or out of view give all-zero depth.
            roi: ``(u0, v0, width, height)``: render only this window of the full frame (same
                pixels as cropping the full-frame render; the window may extend past the sensor).
            shaded: also render the grey image; ``False`` renders depth only (faster).

        Returns:
            :class:`Render` with ``depth`` ``(B, h, w)`` and ``gray`` ``(B, h, w)`` or ``None``;
            ``(h, w)`` is the roi size or the camera size.
        """
        if self._scene is None:
            raise RuntimeError("renderer is closed")
        T = _pose_matrices(poses)
        cam = self.camera if roi is None else self.camera.crop(*check_roi(roi))
        self._cam.fx, self._cam.fy = cam.fx, cam.fy
        self._cam.cx, self._cam.cy = cam.cx + 0.5, cam.cy + 0.5
        P = self._cam.get_projection_matrix(cam.width, cam.height)
        target = self._gl(cam.width, cam.height)
        depth = np.empty((len(T), cam.height, cam.width), dtype=np.float32)
        gray = np.empty_like(depth) if shaded else None
        for b in range(len(T)):
            rgba = target.draw(T[b], P, cam.width, cam.height, shaded, depth[b])
            if shaded:
                gray[b] = _shade(rgba, depth[b] > 0, T[b, :3, :3], self.background)
        return Render(depth=torch.from_numpy(depth), gray=None if gray is None else torch.from_numpy(gray), camera=cam)


def make_renderer(mesh: trimesh.Trimesh, camera: Camera, backend: str = "pyrender", **kwargs):
    """A renderer of ``mesh`` seen by ``camera`` with one of the :data:`BACKENDS`: ``"pyrender"``
    (:class:`Renderer`, OpenGL) or ``"raster"`` (:class:`torchevtrack.raster.RasterRenderer`, a compiled
    CPU z-buffer). Both take the same arguments (``kwargs``: ``znear``, ``zfar``, ``background``) and
    render the same images (see the modules' docstrings)."""
    if backend == "pyrender":
        return Renderer(mesh, camera, **kwargs)
    if backend == "raster":
        from torchevtrack.raster import RasterRenderer  # raster builds on this module

        return RasterRenderer(mesh, camera, **kwargs)
    raise ValueError(f"render backend must be one of {BACKENDS}, got {backend!r}")


class _GLTarget:
    """Direct GL drawing of one pyrender mesh with pyrender's own shader programs and vertex buffers.

    pyrender compiles the programs and uploads the mesh in a first (tiny) render of each kind; after that a
    render only sets the model and projection matrices, draws and reads back, as pyrender's forward pass
    does (same programs, uniforms, GL state and depth conversion, so the same pixels), but without its
    per-call scene traversal and uniform look-ups, and into one framebuffer that only grows: pyrender
    recreates its framebuffers whenever the viewport size changes, which the tracker's windows do at almost
    every update. Back faces are culled (pyrender always culls in depth-only mode; culling in both keeps
    depth-only and shaded silhouettes identical): meshes need outward-facing winding.
    """

    def __init__(self, offscreen: pyrender.OffscreenRenderer, scene: pyrender.Scene, node: pyrender.Node) -> None:
        renderer = offscreen._renderer
        self._primitive = node.mesh.primitives[0]
        camera_node = scene.main_camera_node
        self._znear, self._zfar = camera_node.camera.znear, camera_node.camera.zfar
        view = np.linalg.inv(scene.get_pose(camera_node))
        self._programs = {}
        flags_of = {True: pyrender.RenderFlags.FLAT | pyrender.RenderFlags.RGBA, False: pyrender.RenderFlags.DEPTH_ONLY}
        for shaded, flags in flags_of.items():
            with _single_sampled():
                offscreen.render(scene, flags=flags)  # uploads the mesh, compiles the program
            offscreen._platform.make_current()
            program = renderer._get_primitive_program(self._primitive, flags, pyrender.constants.ProgramFlags.USE_MATERIAL)
            program._bind()
            program.set_uniform("V", view)
            if shaded:
                material = self._primitive.material
                program.set_uniform("material.emissive_factor", material.emissiveFactor)
                program.set_uniform("material.base_color_factor", material.baseColorFactor)
                program.set_uniform("material.metallic_factor", material.metallicFactor)
                program.set_uniform("material.roughness_factor", material.roughnessFactor)
                if material.baseColorTexture is not None:
                    program.set_uniform("material.base_color_texture", 0)  # texture unit 0, bound by draw()
            self._programs[shaded] = (program._program_id, GL.glGetUniformLocation(program._program_id, "M"),
                                      GL.glGetUniformLocation(program._program_id, "P"))
        GL.glUseProgram(0)
        texture = self._primitive.material.baseColorTexture
        self._texture = None if texture is None else texture._texid
        self._framebuffer = GL.glGenFramebuffers(1)
        self._buffers = GL.glGenRenderbuffers(2)
        self._size = (0, 0)

    def reserve(self, width: int, height: int) -> None:
        """Grow the framebuffer to hold ``width x height`` (never shrinks)."""
        if width <= self._size[0] and height <= self._size[1]:
            return
        self._size = (max(width, self._size[0]), max(height, self._size[1]))
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._framebuffer)
        for buffer, storage, attachment in zip(self._buffers, (GL.GL_RGBA, GL.GL_DEPTH_COMPONENT24),
                                               (GL.GL_COLOR_ATTACHMENT0, GL.GL_DEPTH_ATTACHMENT)):
            GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, buffer)
            GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, storage, *self._size)
            GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, attachment, GL.GL_RENDERBUFFER, buffer)

    def draw(self, model: np.ndarray, projection: np.ndarray, width: int, height: int, shaded: bool,
             depth: np.ndarray) -> np.ndarray | None:
        """Render at ``model`` (4x4 object-to-camera), write the metric depth into ``depth`` ``(height, width)``
        float32 and return the RGBA image ``(height, width, 4)`` uint8 when ``shaded``."""
        program, loc_m, loc_p = self._programs[shaded]
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._framebuffer)
        GL.glViewport(0, 0, width, height)
        GL.glEnable(GL.GL_SCISSOR_TEST)  # clear only the viewport
        GL.glScissor(0, 0, width, height)
        GL.glEnable(GL.GL_DEPTH_TEST)
        GL.glDepthMask(GL.GL_TRUE)
        GL.glDepthFunc(GL.GL_LESS)
        GL.glDepthRange(0.0, 1.0)
        GL.glClearColor(0.0, 0.0, 0.0, 0.0)
        GL.glClear(GL.GL_COLOR_BUFFER_BIT | GL.GL_DEPTH_BUFFER_BIT)
        GL.glUseProgram(program)
        GL.glUniformMatrix4fv(loc_m, 1, GL.GL_TRUE, np.ascontiguousarray(model, dtype=np.float32))
        GL.glUniformMatrix4fv(loc_p, 1, GL.GL_TRUE, np.ascontiguousarray(projection, dtype=np.float32))
        GL.glEnable(GL.GL_CULL_FACE)
        GL.glCullFace(GL.GL_BACK)
        GL.glEnable(GL.GL_BLEND)
        GL.glBlendFunc(GL.GL_ONE, GL.GL_ZERO)
        GL.glPolygonMode(GL.GL_FRONT_AND_BACK, GL.GL_FILL)
        if shaded and self._texture is not None:
            GL.glActiveTexture(GL.GL_TEXTURE0)
            GL.glBindTexture(GL.GL_TEXTURE_2D, self._texture)
        primitive = self._primitive
        primitive._bind()
        GL.glDrawElementsInstanced(primitive.mode, primitive.indices.size, GL.GL_UNSIGNED_INT, ctypes.c_void_p(0), 1)
        primitive._unbind()
        GL.glUseProgram(0)
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._framebuffer)
        buffer = GL.glReadPixels(0, 0, width, height, GL.GL_DEPTH_COMPONENT, GL.GL_FLOAT)
        # pyrender's conversion of window depth to metres (same float32 arithmetic), rows flipped to top-down
        window = np.frombuffer(buffer, dtype=np.float32).reshape(height, width)[::-1]
        n, f = self._znear, self._zfar
        np.divide(2.0 * n * f, f + n - (2.0 * window - 1.0) * (f - n), out=depth)
        depth[window == 1.0] = 0.0
        if not shaded:
            return None
        buffer = GL.glReadPixels(0, 0, width, height, GL.GL_RGBA, GL.GL_UNSIGNED_BYTE)
        return np.frombuffer(buffer, dtype=np.uint8).reshape(height, width, 4)[::-1]

    def delete(self) -> None:
        GL.glDeleteFramebuffers(1, [self._framebuffer])
        GL.glDeleteRenderbuffers(2, list(self._buffers))


def _release(offscreen: pyrender.OffscreenRenderer) -> None:
    """Free one offscreen renderer without ending the others.

    pyrender's ``OffscreenRenderer.delete`` calls ``eglTerminate`` on the EGL display, which all
    contexts of the process share, so deleting one renderer would break every other live one. Here
    only this renderer's GL objects and its own context are destroyed.
    """
    platform = offscreen._platform
    platform.make_current()
    offscreen._renderer.delete()
    if hasattr(platform, "_egl_context"):
        from OpenGL.EGL import EGL_NO_CONTEXT, EGL_NO_SURFACE, eglDestroyContext, eglMakeCurrent

        eglMakeCurrent(platform._egl_display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT)
        eglDestroyContext(platform._egl_display, platform._egl_context)
        platform._egl_context = None
        platform._egl_display = None
    else:
        platform.delete_context()
    # leave nothing for pyrender's own __del__ -> delete() to tear down again
    offscreen._renderer = None
    offscreen._platform = None


def _shade(rgba: np.ndarray, mask: np.ndarray, R: np.ndarray, background: float) -> np.ndarray:
    """Lambert grey image from the flat pass: channel 0 albedo, channels 1-3 the object-frame normal
    mapped to [0, 1]. Shape: ``(h, w, 4) uint8, (h, w) bool, (3, 3) -> (h, w) float32``."""
    gray = np.full(mask.shape, background, dtype=np.float32)
    px = rgba[mask].astype(np.float32) * (1.0 / 255.0)
    n = px[:, 1:] * 2.0 - 1.0
    light_obj = (R.T @ LIGHT_DIRECTION).astype(np.float32)  # n_cam . l = n_obj . (R^T l)
    cos = (n @ light_obj) / np.linalg.norm(n, axis=1).clip(1e-6)
    gray[mask] = px[:, 0] * (AMBIENT + (1.0 - AMBIENT) * cos.clip(0.0, None))
    return gray


class ShadingMesh(NamedTuple):
    """The triangles and per-vertex shading attributes every backend interpolates (:func:`shading_mesh`).

    Shape:
        vertices: ``(V, 3)`` float64 metres; faces: ``(F, 3)`` int64, counter-clockwise seen from outside.
        albedo: ``(V,)`` float64 in ``[0, 1]`` (1 on a textured mesh: the texture is its albedo).
        normals: ``(V, 3)`` float64 unit object-frame normals.
        uv: ``(V, 2)`` float64 texture coordinates (``v`` up; repeating outside ``[0, 1]``) or ``None``.
        texture: ``(h, w)`` uint8 luminance image (rows top-down, ``h`` and ``w`` powers of two) or ``None``.
    """

    vertices: np.ndarray
    faces: np.ndarray
    albedo: np.ndarray
    normals: np.ndarray
    uv: np.ndarray | None
    texture: np.ndarray | None


def shading_mesh(mesh: trimesh.Trimesh) -> ShadingMesh:
    """The triangles and per-vertex shading attributes every backend interpolates: normals are smooth
    except across creases sharper than 30 degrees, where vertices are split.

    Albedo: the luminance of a texture image (``TextureVisuals`` with UVs and an image), of the face colours,
    of the vertex colours, or :data:`DEFAULT_ALBEDO`. Textured and face-coloured meshes are shaded as one
    surface: their vertices are merged by position for the normals, then split wherever the faces around a
    vertex need different UVs or albedos.
    """
    texture = _texture_of(mesh)
    if texture is not None:
        uv, image = texture
        vertices, faces, normals, uv = _split_shading(mesh, uv[mesh.faces])
        return ShadingMesh(vertices, faces, np.ones(len(vertices)), normals, uv, image)
    if mesh.visual.kind == "face":
        face_albedo = np.asarray(mesh.visual.face_colors[:, :3], dtype=np.float64) @ _LUMA / 255.0
        vertices, faces, normals, albedo = _split_shading(mesh, np.repeat(face_albedo[:, None, None], 3, axis=1))
        return ShadingMesh(vertices, faces, albedo[:, 0], normals, None, None)
    smooth = trimesh.graph.smooth_shade(mesh, angle=_CREASE_ANGLE)
    if smooth.visual.kind == "vertex":
        albedo = np.asarray(smooth.visual.vertex_colors[:, :3], dtype=np.float64) @ _LUMA / 255.0
    else:
        albedo = np.full(len(smooth.vertices), DEFAULT_ALBEDO)
    return ShadingMesh(np.asarray(smooth.vertices, dtype=np.float64), np.asarray(smooth.faces, dtype=np.int64),
                       albedo, np.asarray(smooth.vertex_normals, dtype=np.float64), None, None)


def _texture_of(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray] | None:
    """UVs ``(V, 2)`` float64 and luminance image ``(h, w)`` uint8 of a textured mesh, else ``None``. The image
    is resized to powers of two (nearest, at most 4096) so both backends build the same mipmaps."""
    visual = mesh.visual
    if visual.kind != "texture" or getattr(visual, "uv", None) is None or len(visual.uv) != len(mesh.vertices):
        return None
    material = visual.material
    image = getattr(material, "image", None)
    if image is None:
        image = getattr(material, "baseColorTexture", None)
    if image is None:
        return None
    if not isinstance(image, Image.Image):
        image = Image.fromarray(np.asarray(image))
    rgb = image.convert("RGB")
    size = tuple(min(4096, 2 ** max(0, round(math.log2(n)))) for n in rgb.size)
    if size != rgb.size:
        rgb = rgb.resize(size, Image.BILINEAR)
    luminance = np.asarray(rgb, dtype=np.float64) @ _LUMA
    return np.asarray(visual.uv, dtype=np.float64), np.clip(np.rint(luminance), 0, 255).astype(np.uint8)


def _split_shading(mesh: trimesh.Trimesh, corner: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                       np.ndarray]:
    """Crease-split smooth shading of ``mesh``'s geometry (vertices merged by position) with the per-corner
    attributes ``corner`` ``(F, 3, k)``: vertices ``(V, 3)``, faces ``(F, 3)`` (``mesh``'s faces, reordered),
    unit normals ``(V, 3)`` and attributes ``(V, k)``, a vertex per distinct (smooth vertex, attribute)."""
    positions, merged = np.unique(np.asarray(mesh.vertices, dtype=np.float64), axis=0, return_inverse=True)
    geometry = trimesh.Trimesh(positions, merged.reshape(-1)[mesh.faces], process=False)
    smooth = trimesh.graph.smooth_shade(geometry, angle=_CREASE_ANGLE)
    # smooth_shade regroups the faces: match them to the input's by their corner positions
    n = len(mesh.faces)
    a = geometry.vertices[geometry.faces].reshape(n, 9)
    b = np.asarray(smooth.vertices)[smooth.faces].reshape(n, 9)
    order = np.empty(n, dtype=np.int64)
    order[np.lexsort(b.T[::-1])] = np.lexsort(a.T[::-1])
    if not np.array_equal(a[order], b):
        raise ValueError("mesh could not be prepared for shading (faces changed by smoothing)")
    k = corner.shape[-1]
    keys = np.concatenate((np.asarray(smooth.faces, dtype=np.float64).reshape(-1, 1),
                           corner[order].reshape(-1, k)), axis=1)
    unique, inverse = np.unique(keys, axis=0, return_inverse=True)
    vid = unique[:, 0].astype(np.int64)
    return (np.asarray(smooth.vertices, dtype=np.float64)[vid], inverse.reshape(n, 3).astype(np.int64),
            np.asarray(smooth.vertex_normals, dtype=np.float64)[vid], unique[:, 1:])


def _pyrender_mesh(mesh: trimesh.Trimesh) -> pyrender.Mesh:
    """pyrender mesh of :func:`shading_mesh` whose vertex colours carry (albedo, normal * 0.5 + 0.5) for
    the flat pass; a texture becomes the base colour texture (luminance in red, 1 in green, blue and alpha),
    which the flat pass multiplies into those colours (trilinear mipmapped sampling, repeating)."""
    shading = shading_mesh(mesh)
    attributes = np.concatenate((shading.albedo[:, None], shading.normals * 0.5 + 0.5), axis=1)
    texture = None
    if shading.texture is not None:
        rgba = np.full((*shading.texture.shape, 4), 255, dtype=np.uint8)
        rgba[..., 0] = shading.texture
        texture = pyrender.Texture(source=rgba, source_channels="RGBA")
    material = pyrender.MetallicRoughnessMaterial(baseColorFactor=(1.0, 1.0, 1.0, 1.0), alphaMode="OPAQUE",
                                                  baseColorTexture=texture)
    primitive = pyrender.Primitive(
        positions=shading.vertices.astype(np.float32),
        normals=shading.normals.astype(np.float32),
        texcoord_0=None if shading.uv is None else shading.uv.astype(np.float32),
        color_0=attributes.astype(np.float32),
        indices=shading.faces.astype(np.uint32),
        material=material,
        mode=pyrender.constants.GLTF.TRIANGLES,
    )
    return pyrender.Mesh(primitives=[primitive])


def check_renderer_args(mesh: trimesh.Trimesh, camera: Camera, znear: float, zfar: float,
                        background: float) -> None:
    """The constructor checks every backend shares (see :class:`Renderer`): a one-line ``TypeError`` /
    ``ValueError`` for the first bad argument, else ``None``."""
    if not isinstance(mesh, trimesh.Trimesh):
        raise TypeError(f"mesh must be a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0:
        raise ValueError("mesh has no faces")
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a torchevtrack Camera, got {type(camera).__name__}")
    if not (0.0 < znear < zfar and math.isfinite(zfar)):
        raise ValueError(f"need 0 < znear < zfar < inf, got znear={znear}, zfar={zfar}")
    if not math.isfinite(background):
        raise ValueError(f"background must be a finite grey value, got {background}")


def _pose_matrices(poses: torch.Tensor) -> np.ndarray:
    """Validated ``(B, 4, 4)`` float64 object-to-camera (OpenCV) transforms."""
    return pose_to_matrix(torch.from_numpy(unit_poses(poses))).numpy()


def unit_poses(poses: torch.Tensor) -> np.ndarray:
    """Validated ``(B, 7)`` float64 poses (a ``(7,)`` pose as one row) with their quaternions normalised (numpy: a
    render's few numbers); a one-line ``ValueError`` / ``TypeError`` for bad poses."""
    poses = torch.as_tensor(poses)
    if poses.ndim == 1:
        poses = poses[None]
    if poses.ndim != 2 or poses.shape[-1] != 7:
        raise ValueError(f"poses must have shape (B, 7) or (7,) [tx, ty, tz, qw, qx, qy, qz], got {tuple(poses.shape)}")
    if not poses.is_floating_point():
        raise TypeError(f"poses must be a floating-point tensor, got {poses.dtype}")
    p = np.array(poses.detach().cpu().numpy(), dtype=np.float64)  # a copy
    if not np.isfinite(p).all():
        raise ValueError("poses contain NaN or infinite values")
    norm = _normalise_quaternions(p)
    if (np.abs(norm - 1) > 1e-3).any():
        raise ValueError(f"pose quaternions must be unit norm, got |q| = {norm.tolist()}")
    return p


def _normalise_quaternions(p: np.ndarray) -> np.ndarray:
    """Divide the quaternions of poses ``(B, 7)`` by their norms, in place, and return those norms ``(B,)`` (the
    one rule by which renders normalise their poses)."""
    norm = np.empty(p.shape[0])
    nb_normalise_quaternions(p, norm)
    return norm


def check_roi(roi) -> tuple[int, int, int, int]:
    """A render's ``roi`` ``(u0, v0, width, height)`` as four ints (positive size; a one-line ``ValueError``
    otherwise)."""
    try:
        u0, v0, w, h = (int(x) for x in roi)
        exact = all(float(x) == int(x) for x in roi)
    except (TypeError, ValueError):
        raise ValueError(f"roi must be (u0, v0, width, height) integers, got {roi!r}") from None
    if not exact or w <= 0 or h <= 0:
        raise ValueError(f"roi must be (u0, v0, width, height) integers with positive size, got {roi!r}")
    return u0, v0, w, h
