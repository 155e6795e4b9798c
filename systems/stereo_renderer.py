"""Rendered stereo frames: each eye's image through Drake's VTK renderer, from the
eye's off-axis camera (``StereoView``), handed to a sink (the video writer).

Rendering goes through the QueryObject of the virtual world's SceneGraph with a
camera built per frame (intrinsics change with the eye's position, which a
fixed RgbdSensor cannot do). Images are a publish at their own rate; in a
real-time run they may be decimated (frames skipped while rendering would take
more than ``max_wall_share`` of the wall clock), the views never are.
"""

from __future__ import annotations

import math
import time
from typing import Callable, Optional

import numpy as np
from pydrake.common import MemoryFile
from pydrake.common.value import AbstractValue
from pydrake.geometry import (
    ClippingRange, ColorRenderCamera, DepthRange, DepthRenderCamera, GeometryId, InMemoryMesh,
    LightParameter, MakeRenderEngineVtk, Mesh, PerceptionProperties, QueryObject,
    RenderCameraCore, RenderEngineVtkParams, Rgba)
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import CameraInfo, ImageDepth32F, ImageRgba8U

from maglev_haptics.systems.rotations import rotation_matrix
from maglev_haptics.systems.stereo import CAMERA_SIZE

RENDERER_NAME = "stereo_display"
BACKGROUND_RGB = (0.0, 0.0, 0.0)  # what the display shows where nothing is (black)
# Drake 1.51's VTK engine takes the principal point with pixel k's centre at k + 0.5
# (the image's corner at 0), while CameraInfo documents centres at integers: a
# sphere on the optical axis lands half a pixel up and left. Measured, and checked
# by the render test in tests/test_stereo.py.
VTK_PRINCIPAL_POINT_SHIFT_PX = 0.5


def AddStereoRenderer(scene_graph, background_rgb=BACKGROUND_RGB) -> None:
    """Give ``scene_graph`` the VTK engine the stereo display renders with (before Build).

    Its light is a point at the eye: VTK's default headlight shines along the camera's
    axis, which for an off-axis eye is the screen's normal, not the line of sight, and
    would leave the side of an object the eye sees obliquely in the dark.
    """
    scene_graph.AddRenderer(RENDERER_NAME, _make_engine(background_rgb))


def canvas_extent(center_px: float, size_px: int):
    """(canvas size, image offset) along one axis (px): Drake's cameras need the
    principal point inside the image, but an eye beside the display has it outside
    (off-axis); the image is then cut from a larger canvas that holds both."""
    offset = max(0, math.floor(-center_px) + 1)
    return max(size_px + offset, math.floor(center_px + offset) + 2), offset


def render_camera(camera: np.ndarray, display_px, image_px, near_m: float, far_m: float):
    """(ColorRenderCamera, X_WC, (column, row) offset of the image in the canvas) for an
    eye camera vector [q_WC, p_WC, fx, fy, cx, cy] given at the display's resolution
    ``display_px`` (width, height), for an image of ``image_px``: the same view, scaled."""
    q, p, (fx, fy, cx, cy) = camera[0:4], camera[4:7], camera[7:11]
    sx, sy = image_px[0] / display_px[0], image_px[1] / display_px[1]
    cx = (cx + 0.5) * sx - 0.5 + VTK_PRINCIPAL_POINT_SHIFT_PX
    cy = (cy + 0.5) * sy - 0.5 + VTK_PRINCIPAL_POINT_SHIFT_PX
    width, column = canvas_extent(cx, int(image_px[0]))
    height, row = canvas_extent(cy, int(image_px[1]))
    info = CameraInfo(width, height, fx * sx, fy * sy, cx + column, cy + row)
    core = RenderCameraCore(RENDERER_NAME, info, ClippingRange(near_m, far_m), RigidTransform())
    X_WC = RigidTransform(rotation_matrix(q), p)
    return ColorRenderCamera(core, False), X_WC, (column, row)


def vertex_normals(positions: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit normals (n, 3) of a triangle mesh's vertices: the area-weighted sum of
    their triangles' normals (counter-clockwise faces point out)."""
    a, b, c = (positions[triangles[:, k]] for k in range(3))
    face = np.cross(b - a, c - a)  # |face| = twice the area
    normals = np.zeros_like(positions)
    for k in range(3):
        np.add.at(normals, triangles[:, k], face)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)


class SurfaceLayer:
    """A deformable surface drawn into the stereo images: it is no SceneGraph geometry
    (the lattice moves its vertices every tick), so it lives in a VTK engine of its
    own, re-registered as a mesh each frame, rendered with each eye's camera and laid
    over the scene's image wherever it is nearer (by depth).

    ``triangles`` (T, 3) index the rows of the surface's vertex positions (n, 3).
    """

    def __init__(self, triangles: np.ndarray, rgba):
        self._triangles = np.asarray(triangles, dtype=np.int64)
        self.vertex_count = int(self._triangles.max()) + 1
        self._engine = _make_engine(BACKGROUND_RGB)
        self._properties = PerceptionProperties()
        self._properties.AddProperty("phong", "diffuse", Rgba(*rgba))
        faces = self._triangles + 1  # OBJ counts from 1
        self._face_text = "".join(f"f {a}//{a} {b}//{b} {c}//{c}\n" for a, b, c in faces)
        self._geometry = None

    def update(self, positions: np.ndarray) -> None:
        """Replace the mesh by one with these vertex positions (n, 3) (m, W)."""
        positions = np.asarray(positions, float).reshape(-1, 3)
        normals = vertex_normals(positions, self._triangles)
        n = len(positions)
        text = (("v %.6f %.6f %.6f\n" * n) % tuple(positions.ravel())
                + ("vn %.4f %.4f %.4f\n" * n) % tuple(normals.ravel()) + self._face_text)
        if self._geometry is not None:
            self._engine.RemoveGeometry(self._geometry)
        self._geometry = GeometryId.get_new_id()
        mesh = Mesh(InMemoryMesh(mesh_file=MemoryFile(text, ".obj", "deformable_surface")))
        self._engine.RegisterVisual(self._geometry, mesh, self._properties, RigidTransform(),
                                    False)

    def overlay(self, color: np.ndarray, depth: np.ndarray, camera, X_WC) -> None:
        """Draw the surface into ``color`` (canvas RGBA, in place) where it is nearer than
        the scene's ``depth`` (canvas, m)."""
        core = camera.core()
        info = core.intrinsics()
        own_color = ImageRgba8U(info.width(), info.height())
        own_depth = ImageDepth32F(info.width(), info.height())
        self._engine.UpdateViewpoint(X_WC)
        self._engine.RenderColorImage(camera, own_color)
        self._engine.RenderDepthImage(_depth_camera(core), own_depth)
        nearer = own_depth.data[:, :, 0] < depth
        color[nearer] = own_color.data[nearer]


def _make_engine(background_rgb):
    return MakeRenderEngineVtk(RenderEngineVtkParams(
        default_clear_color=list(background_rgb),
        lights=[LightParameter(type="point", frame="camera", position=[0.0, 0.0, 0.0])]))


def _depth_camera(core) -> DepthRenderCamera:
    near, far = core.clipping().near(), core.clipping().far()
    return DepthRenderCamera(core, DepthRange(near, far))


class StereoRenderer(LeafSystem):
    """Renders both eyes at ``rate_hz`` and passes them to ``sink(t, left, right)``
    (uint8 RGB arrays, height x width x 3).

    .. pydrake_system::

        name: StereoRenderer
        input_ports:
        - query_object
        - camera_left
        - camera_right
        - view_ok

    ``max_wall_share``: None renders every frame; a share in (0, 1] skips a frame
    whenever the rendering so far took more than that share of the wall time since
    the first frame (for real-time runs). ``frames_rendered`` and
    ``frames_skipped`` count them; ``render_wall_s`` is the time spent rendering.
    ``wall_clock`` () -> s is the clock both are read from (tests give their own).
    """

    def __init__(self, *, rate_hz: float, image_px, display_px, near_m: float, far_m: float,
                 sink: Callable[[float, np.ndarray, np.ndarray], None],
                 max_wall_share: Optional[float] = None,
                 surface: Optional[SurfaceLayer] = None,
                 wall_clock: Callable[[], float] = time.perf_counter):
        super().__init__()
        self._image_px = (int(image_px[0]), int(image_px[1]))
        self._display_px = tuple(display_px)
        self._near_m, self._far_m = near_m, far_m
        self._sink = sink
        self._max_wall_share = max_wall_share
        self._wall_clock = wall_clock
        self._query = self.DeclareAbstractInputPort(
            "query_object", AbstractValue.Make(QueryObject()))
        self._cameras = [self.DeclareVectorInputPort(f"camera_{eye}", CAMERA_SIZE)
                         for eye in ("left", "right")]
        self._view_ok = self.DeclareVectorInputPort("view_ok", 1)
        self._surface = surface
        if surface is not None:
            self._surface_positions = self.DeclareVectorInputPort(
                "surface_positions_m", 3 * surface.vertex_count)
        self.DeclarePeriodicPublishEvent(1.0 / rate_hz, 0.0, self._publish)
        self.frames_rendered = 0
        self.frames_skipped = 0
        self.render_wall_s = 0.0
        self._first_wall_s = None

    def render(self, context):
        """(left, right) RGB images of the current views."""
        query = self._query.Eval(context)
        world = query.inspector().world_frame_id()
        if self._surface is not None:
            self._surface.update(self._surface_positions.Eval(context))
        images = []
        for port in self._cameras:
            camera, X_WC, (column, row) = render_camera(
                port.Eval(context), self._display_px, self._image_px, self._near_m, self._far_m)
            canvas = query.RenderColorImage(camera, world, X_WC).data
            if self._surface is not None:
                canvas = canvas.copy()
                depth = query.RenderDepthImage(_depth_camera(camera.core()), world, X_WC).data
                self._surface.overlay(canvas, depth[:, :, 0], camera, X_WC)
            width, height = self._image_px
            images.append(np.array(canvas[row:row + height, column:column + width, 0:3]))
        return images

    def _publish(self, context):
        if self._view_ok.Eval(context)[0] < 0.5:
            return
        now = self._wall_clock()
        if self._first_wall_s is None:
            self._first_wall_s = now
        elif (self._max_wall_share is not None
              and self.render_wall_s > self._max_wall_share * (now - self._first_wall_s)):
            self.frames_skipped += 1
            return
        left, right = self.render(context)
        self.render_wall_s += self._wall_clock() - now
        self.frames_rendered += 1
        self._sink(context.get_time(), left, right)
