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
from pydrake.common.eigen_geometry import Quaternion
from pydrake.common.value import AbstractValue
from pydrake.geometry import (
    ClippingRange, ColorRenderCamera, LightParameter, MakeRenderEngineVtk, QueryObject, RenderCameraCore,
    RenderEngineVtkParams)
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import CameraInfo

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
    scene_graph.AddRenderer(RENDERER_NAME, MakeRenderEngineVtk(RenderEngineVtkParams(
        default_clear_color=list(background_rgb),
        lights=[LightParameter(type="point", frame="camera", position=[0.0, 0.0, 0.0])])))


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
    X_WC = RigidTransform(RotationMatrix(Quaternion(q / np.linalg.norm(q))), p)
    return ColorRenderCamera(core, False), X_WC, (column, row)


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
    """

    def __init__(self, *, rate_hz: float, image_px, display_px, near_m: float, far_m: float,
                 sink: Callable[[float, np.ndarray, np.ndarray], None],
                 max_wall_share: Optional[float] = None):
        super().__init__()
        self._image_px = (int(image_px[0]), int(image_px[1]))
        self._display_px = tuple(display_px)
        self._near_m, self._far_m = near_m, far_m
        self._sink = sink
        self._max_wall_share = max_wall_share
        self._query = self.DeclareAbstractInputPort(
            "query_object", AbstractValue.Make(QueryObject()))
        self._cameras = [self.DeclareVectorInputPort(f"camera_{eye}", CAMERA_SIZE)
                         for eye in ("left", "right")]
        self._view_ok = self.DeclareVectorInputPort("view_ok", 1)
        self.DeclarePeriodicPublishEvent(1.0 / rate_hz, 0.0, self._publish)
        self.frames_rendered = 0
        self.frames_skipped = 0
        self.render_wall_s = 0.0
        self._first_wall_s = None

    def render(self, context):
        """(left, right) RGB images of the current views."""
        query = self._query.Eval(context)
        world = query.inspector().world_frame_id()
        images = []
        for port in self._cameras:
            camera, X_WC, (column, row) = render_camera(
                port.Eval(context), self._display_px, self._image_px, self._near_m, self._far_m)
            canvas = query.RenderColorImage(camera, world, X_WC).data
            width, height = self._image_px
            images.append(np.array(canvas[row:row + height, column:column + width, 0:3]))
        return images

    def _publish(self, context):
        if self._view_ok.Eval(context)[0] < 0.5:
            return
        now = time.perf_counter()
        if self._first_wall_s is None:
            self._first_wall_s = now
        elif (self._max_wall_share is not None
              and self.render_wall_s > self._max_wall_share * (now - self._first_wall_s)):
            self.frames_skipped += 1
            return
        left, right = self.render(context)
        self.render_wall_s += time.perf_counter() - now
        self.frames_rendered += 1
        self._sink(context.get_time(), left, right)
