"""Per-eye views of the co-located display (paper Section IV and V.C).

The display is a window into W: each eye sees the virtual world through the
display's active rectangle, so each eye's view is an off-axis frustum from the
eye through that rectangle (Kooima, "Generalized Perspective Projection").
Points on the display plane land on the same pixel for both eyes (zero
parallax); points below it have uncrossed disparity.

The numeric core is plain functions; ``StereoView`` runs them at the view rate
on the predicted glasses pose.

Pixel convention (Drake's ``CameraInfo``): pixel (u, v) = (column, row) has its
centre at integer coordinates, u to the image's right (the display's x), v down
(against the display's y), so the rectangle spans -0.5 .. W - 0.5.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numba
import numpy as np
from pydrake.math import RollPitchYaw, RotationMatrix
from pydrake.systems.framework import LeafSystem

from maglev_haptics.hardware.kernels import MATRIX, SCALAR, VECTOR, kernel
from maglev_haptics.systems.rotations import rotation_matrix

# An eye must be at least this far in front of the display plane (m): nearer, the
# frustum degenerates (and a real eye 1 cm from a screen sees no image anyway).
MIN_EYE_DISTANCE_M = 0.01
CAMERA_SIZE = 11  # [q_WC (4), p_WC (3), fx, fy, cx, cy (px)]


@dataclass(frozen=True)
class DisplayRectangle:
    """The active area in W: corners lower-left pa, lower-right pb, upper-left pc (m),
    and its resolution (px)."""

    pa: np.ndarray
    pb: np.ndarray
    pc: np.ndarray
    width_px: int
    height_px: int

    @cached_property
    def axes(self):
        """(vr, vu, vn): unit vectors right, up and out of the screen."""
        return screen_axes(self.pa, self.pb, self.pc)

    @cached_property
    def size_m(self):
        """(width, height) of the active area (m)."""
        return float(np.linalg.norm(self.pb - self.pa)), float(np.linalg.norm(self.pc - self.pa))

    @cached_property
    def R_WC(self) -> np.ndarray:
        """(3, 3) every eye camera C's orientation in W (``eye_camera``: C looks into the
        screen, x right, y down; the same for any eye)."""
        vr, vu, vn = self.axes
        return np.column_stack([vr, -vu, -vn])

    @cached_property
    def q_WC(self) -> np.ndarray:
        """``R_WC`` as [w, x, y, z]."""
        q = RotationMatrix(self.R_WC).ToQuaternion()
        return np.array([q.w(), q.x(), q.y(), q.z()])

    @property
    def corners_W(self) -> np.ndarray:
        """(4, 3) lower-left, lower-right, upper-right, upper-left (m)."""
        return np.array([self.pa, self.pb, self.pb + self.pc - self.pa, self.pc])


def display_rectangle(display) -> DisplayRectangle:
    """The active area of a ``DisplaySpec``; ValueError naming the field when it has no area."""
    width, height = (float(v) for v in display.size_m)
    if not (math.isfinite(width) and math.isfinite(height) and width > 0 and height > 0):
        raise ValueError(f"device.display.size_m = {list(display.size_m)}: the active area "
                         "needs a positive, finite width and height (m)")
    columns, rows = display.resolution_px
    if not (isinstance(columns, int) and isinstance(rows, int) and columns > 0 and rows > 0):
        raise ValueError(f"device.display.resolution_px = {list(display.resolution_px)}: "
                         "must be two positive integers (width, height)")
    pose = np.asarray(display.pose_W, float)
    R_WD = RollPitchYaw(pose[3:6]).ToRotationMatrix().matrix()

    def corner(x, y):
        return pose[0:3] + R_WD @ np.array([x, y, 0.0])

    return DisplayRectangle(pa=corner(-width / 2, -height / 2), pb=corner(width / 2, -height / 2),
                            pc=corner(-width / 2, height / 2), width_px=columns, height_px=rows)


def _cross(a, b) -> np.ndarray:
    # np.cross costs ~50 us on 3-vectors (axis bookkeeping); this ~1 us.
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


def screen_axes(pa, pb, pc):
    """Unit vectors (vr, vu, vn): right, up and out of the screen (toward the viewer)."""
    vr = np.asarray(pb, float) - pa
    vu = np.asarray(pc, float) - pa
    vr = vr / math.sqrt(vr @ vr)
    vu = vu / math.sqrt(vu @ vu)
    vn = _cross(vr, vu)
    return vr, vu, vn / math.sqrt(vn @ vn)


def eye_distance_m(pa, pb, pc, pe) -> float:
    """Signed distance (m) of the eye pe in front of the display plane."""
    pa = np.asarray(pa, float)
    _, _, vn = screen_axes(pa, pb, pc)
    return _eye_distance(pa, vn, np.asarray(pe, float))


def _check_distance(distance: float, pe) -> float:
    """``distance`` (m) of the eye pe in front of the display, if it can see it."""
    if not distance >= MIN_EYE_DISTANCE_M:
        raise ValueError(
            f"eye at {np.round(np.asarray(pe, float), 4).tolist()} m is {distance * 1e3:.1f} mm "
            f"in front of the display plane: an eye must be at least "
            f"{MIN_EYE_DISTANCE_M * 1e3:.0f} mm in front of it (above the screen) to see it")
    return distance


def check_clipping(near, far, field_name: str = "near, far") -> None:
    if not (0 < near < far and math.isfinite(far)):
        raise ValueError(f"{field_name} = {near}, {far}: need 0 < near < far < inf (m)")


@numba.njit(cache=True)
def _dot3(a, b) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@numba.njit(cache=True)
def _eye_distance(pa, vn, pe) -> float:
    """Signed distance (m) of the eye pe in front of the screen through pa, normal vn."""
    return _dot3(pe - pa, vn)


@numba.njit(cache=True)
def _projection_into(pa, pb, pc, vr, vu, vn, pe, distance, near, far, out) -> None:
    """Kooima's P M^T T of the eye pe, ``distance`` (m) in front of the screen, into
    ``out`` (4x4), written out for its zeros."""
    va, vb, vc = pa - pe, pb - pe, pc - pe
    scale = near / distance
    left, right = _dot3(vr, va) * scale, _dot3(vr, vb) * scale
    bottom, top = _dot3(vu, va) * scale, _dot3(vu, vc) * scale
    # P's rows mix at most two rows of [M^T T] = [vr, vu, vn | -axis . pe; 0 0 0 1].
    rows = np.empty((3, 4))
    for i, axis in enumerate((vr, vu, vn)):
        rows[i, 0:3] = axis
        rows[i, 3] = -_dot3(axis, pe)
    a, b = 2 * near / (right - left), (right + left) / (right - left)
    c, d = 2 * near / (top - bottom), (top + bottom) / (top - bottom)
    e, f = -(far + near) / (far - near), -2 * far * near / (far - near)
    out[0, :] = a * rows[0] + b * rows[2]
    out[1, :] = c * rows[1] + d * rows[2]
    out[2, :] = e * rows[2]
    out[2, 3] += f
    out[3, :] = -rows[2]


@numba.njit(cache=True)
def _intrinsics(pa, vr, vu, width_m, height_m, pe, distance, width_px, height_px):
    """(fx, fy, cx, cy) (px) of the camera of the eye pe, ``distance`` (m) in front of
    the screen (``eye_camera``)."""
    return (distance * width_px / width_m, distance * height_px / height_m,
            _dot3(pe - pa, vr) / width_m * width_px - 0.5,
            (height_m - _dot3(pe - pa, vu)) / height_m * height_px - 0.5)


@kernel((MATRIX, VECTOR, VECTOR, VECTOR, VECTOR, VECTOR, VECTOR, SCALAR, SCALAR, SCALAR, SCALAR,
         SCALAR, SCALAR, VECTOR, VECTOR))
def view_state_into(eyes_W, pa, pb, pc, vr, vu, vn, width_m, height_m, width_px, height_px,
                    near, far, q_WC, out):
    """``StereoView``'s state for the eyes (2, 3) into ``out``: the eyes, both
    projections (row-major) and both cameras, then view_ok 1. Returns (-1, 0.0), or
    (k, its distance (m)) for an eye k nearer the screen than MIN_EYE_DISTANCE_M, with
    ``out`` untouched."""
    distances = np.array([_eye_distance(pa, vn, eyes_W[0]), _eye_distance(pa, vn, eyes_W[1])])
    for k in range(2):
        if not distances[k] >= MIN_EYE_DISTANCE_M:
            return k, distances[k]
    out[0:6] = eyes_W.ravel()
    projection = np.empty((4, 4))
    for k in range(2):
        pe = eyes_W[k].copy()
        _projection_into(pa, pb, pc, vr, vu, vn, pe, distances[k], near, far, projection)
        out[6 + 16 * k:22 + 16 * k] = projection.ravel()
        camera = out[38 + CAMERA_SIZE * k:38 + CAMERA_SIZE * (k + 1)]
        camera[0:4] = q_WC
        camera[4:7] = pe
        camera[7], camera[8], camera[9], camera[10] = _intrinsics(
            pa, vr, vu, width_m, height_m, pe, distances[k], width_px, height_px)
    out[38 + 2 * CAMERA_SIZE] = 1.0
    return -1, 0.0


def off_axis_projection(pa, pb, pc, pe, near, far) -> np.ndarray:
    """4x4 OpenGL projection P M^T T of the eye pe looking through the screen
    (corners lower-left pa, lower-right pb, upper-left pc; all in W, m), with the
    clipping planes ``near`` and ``far`` (m from the eye, along the screen normal).

    Kooima's generalized perspective projection: T moves the eye to the origin,
    M^T turns W into screen axes, P is the frustum through the screen's edges.
    Raises ValueError for an eye on or behind the screen, or bad clipping planes.
    """
    check_clipping(near, far)
    pa, pb, pc, pe = (np.asarray(v, float) for v in (pa, pb, pc, pe))
    vr, vu, vn = screen_axes(pa, pb, pc)
    distance = _check_distance(_eye_distance(pa, vn, pe), pe)
    projection = np.empty((4, 4))
    _projection_into(pa, pb, pc, vr, vu, vn, pe, distance, float(near), float(far), projection)
    return projection


def eye_camera(screen: DisplayRectangle, pe, width_px: int, height_px: int):
    """The pinhole camera equivalent to the eye's off-axis view, for an image of
    width_px x height_px covering the active area.

    Returns (R_WC (3x3), p_WC (m), fx, fy, cx, cy (px)): C looks into the screen
    (Cz = -vn), its x along the screen's right, y along its down; the principal
    point is the foot of the eye's perpendicular on the screen, off centre.
    """
    vr, vu, vn = screen.axes
    pe = np.asarray(pe, float)
    distance = _check_distance(_eye_distance(screen.pa, vn, pe), pe)
    fx, fy, cx, cy = _intrinsics(screen.pa, vr, vu, *screen.size_m, pe, distance,
                                 float(width_px), float(height_px))
    return screen.R_WC, pe, fx, fy, cx, cy


def projected_pixel(projection: np.ndarray, p_W, width_px: int, height_px: int) -> np.ndarray:
    """(u, v) pixel of the W point p_W under an OpenGL projection (NDC to window)."""
    clip = projection @ np.append(np.asarray(p_W, float), 1.0)
    x, y = clip[0] / clip[3], clip[1] / clip[3]
    return np.array([(x + 1) / 2 * width_px - 0.5, (1 - y) / 2 * height_px - 0.5])


def screen_point(screen: DisplayRectangle, pe, p_W) -> np.ndarray:
    """Where the line from the eye pe through p_W meets the display plane (W, m)."""
    pe, p_W = np.asarray(pe, float), np.asarray(p_W, float)
    _, _, vn = screen.axes
    ray = p_W - pe
    along = np.dot(ray, vn)
    if abs(along) < 1e-12:
        raise ValueError(f"the line from the eye {pe.tolist()} through {p_W.tolist()} runs "
                         "parallel to the display: it meets it nowhere")
    return pe + ray * (np.dot(screen.pa - pe, vn) / along)


def screen_pixel(screen: DisplayRectangle, p_S) -> np.ndarray:
    """(u, v) pixel of a point p_S on the display plane, at the display's resolution."""
    vr, vu, _ = screen.axes
    width_m, height_m = screen.size_m
    offset = np.asarray(p_S, float) - screen.pa
    return np.array([np.dot(offset, vr) / width_m * screen.width_px - 0.5,
                     (height_m - np.dot(offset, vu)) / height_m * screen.height_px - 0.5])


def eye_positions_W(q_WG, p_WG, ipd_m: float) -> np.ndarray:
    """(2, 3) left and right eye centres (m): -/+ IPD/2 along the glasses' x."""
    x_G = rotation_matrix(q_WG).col(0)
    return np.array([p_WG - x_G * ipd_m / 2, p_WG + x_G * ipd_m / 2])


def check_ipd(ipd_m: float, field_name: str = "device.glasses.ipd_m") -> None:
    """Adult interpupillary distances lie within 40-80 mm; anything else is a typo."""
    if not (isinstance(ipd_m, (int, float)) and 0.040 <= ipd_m <= 0.080):
        raise ValueError(f"{field_name} = {ipd_m}: must be within 0.040-0.080 m "
                         "(adult interpupillary distances)")


class StereoView(LeafSystem):
    """Both eyes' off-axis views from the glasses pose, at the view rate.

    .. pydrake_system::

        name: StereoView
        input_ports:
        - X_WG
        output_ports:
        - eye_positions_W
        - projection_left
        - projection_right
        - camera_left
        - camera_right
        - view_ok

    ``X_WG`` is the glasses pose [qw, qx, qy, qz, x, y, z] to draw for (the
    predictor's). Outputs, held between view updates (state): the eyes' centres
    (6, m), each eye's 4x4 OpenGL projection (16, row-major; clip coordinates
    from W), each eye's pinhole camera (CAMERA_SIZE: pose of C in W and the
    intrinsics at the display's resolution, px), and ``view_ok`` (1 when this
    update's pose gave a view). A pose with NaN, or an eye not in front of the
    display, keeps the last good view (the image freezes rather than breaks).
    """

    def __init__(self, *, screen: DisplayRectangle, ipd_m: float, period_s: float,
                 near_m: float, far_m: float):
        super().__init__()
        check_ipd(ipd_m)
        check_clipping(near_m, far_m)
        self._screen = screen
        self.view_period_s = period_s
        self._ipd_m = ipd_m
        self._near_m = near_m
        self._far_m = far_m
        self._X_WG = self.DeclareVectorInputPort("X_WG", 7)
        self._layout = {"eye_positions_W": slice(0, 6), "projection_left": slice(6, 22),
                        "projection_right": slice(22, 38),
                        "camera_left": slice(38, 38 + CAMERA_SIZE),
                        "camera_right": slice(38 + CAMERA_SIZE, 38 + 2 * CAMERA_SIZE),
                        "view_ok": slice(38 + 2 * CAMERA_SIZE, 39 + 2 * CAMERA_SIZE)}
        self._state = self.DeclareDiscreteState(39 + 2 * CAMERA_SIZE)
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, 0.0, self._update)
        for name, rows in self._layout.items():
            self.DeclareVectorOutputPort(
                name, rows.stop - rows.start,
                lambda context, output, rows=rows: output.SetFromVector(
                    context.get_discrete_state(self._state).value()[rows]),
                {self.discrete_state_ticket(self._state)})

    def view_vector(self, q_WG, p_WG) -> np.ndarray:
        """The state vector for a glasses pose; ValueError if an eye cannot see the display."""
        s = self._screen
        eyes = eye_positions_W(q_WG, p_WG, self._ipd_m)
        view = np.empty(39 + 2 * CAMERA_SIZE)
        eye, distance = view_state_into(
            eyes, s.pa, s.pb, s.pc, *s.axes, *s.size_m, float(s.width_px), float(s.height_px),
            float(self._near_m), float(self._far_m), s.q_WC, view)
        if eye >= 0:
            _check_distance(distance, eyes[eye])
        return view

    def _update(self, context, discrete_state):
        x_WG = self._X_WG.Eval(context)
        state = discrete_state.get_mutable_vector(self._state)
        try:
            if not np.all(np.isfinite(x_WG)):
                raise ValueError("no glasses pose")
            state.SetFromVector(self.view_vector(x_WG[0:4], x_WG[4:7]))
        except ValueError:
            state.SetAtIndex(self._layout["view_ok"].start, 0.0)
