"""Meshcat drawing of the device: coils coloured by current, commanded and measured
poses, and the force rendered on the user's hand."""

from __future__ import annotations

import numpy as np
from pydrake.geometry import Cylinder, Meshcat, Rgba, Sphere
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.systems.framework import LeafSystem

from maglev_haptics.systems.rotations import rigid_transform

COIL_PATH = "/device/coils"
SETPOINT_PATH = "/device/setpoint"
MEASURED_PATH = "/device/measured"
MARKERS_PATH = "/device/markers_measured"
FORCE_PATH = "/device/rendered_force"
FORCE_SCALE_M_PER_N = 0.05  # arrow length per newton of rendered force (m/N)
FORCE_SHOWN_N = 0.005  # smaller rendered forces are not drawn (N)
COLOR_STEPS = 64  # coil colours are sent when they change by a step of this many


def current_colors(currents_a: np.ndarray, limit_a: float, opacity: float = 1.0) -> np.ndarray:
    """(n, 4) RGBA per coil: grey at 0 A, red for positive, blue for negative, full at
    the limit. The square root makes the ~1-2 A of hovering clearly visible against a
    4 A scale. Whole arrays at once: per coil in numpy it cost ~0.4 ms a frame.
    """
    currents_a = np.asarray(currents_a, dtype=float)
    level = np.sqrt(np.clip(np.abs(currents_a) / limit_a, 0.0, 1.0))[:, None]
    grey = np.array([0.6, 0.6, 0.6])
    hot = np.where(currents_a[:, None] >= 0, [0.9, 0.1, 0.05], [0.05, 0.25, 0.95])
    rgb = grey + level * (hot - grey)
    return np.column_stack((rgb, np.full(len(currents_a), opacity)))


class DeviceVisualizer(LeafSystem):
    """Draws what the MultibodyPlant's geometry does not show, at ``period_s``.

    .. pydrake_system::

        name: DeviceVisualizer
        input_ports:
        - coil_currents
        - setpoint
        - X_WI_measured
        - markers_measured
        - wrench_rendered_W

    Coils are drawn as cylinders under the display (their tops at z = p_WA z),
    coloured by current (red +, blue -, saturated at the limit); a triad marks
    the commanded pose and another the measured one; the measured markers (in the
    tracker's frame T, drawn in W through ``tracker.X_WT``) are small spheres; an orange
    rod from the measured instrument origin shows the force rendered on the user's hand
    (FORCE_SCALE_M_PER_N).
    """

    def __init__(self, *, meshcat: Meshcat, device, period_s: float = 1 / 30,
                 close_view: bool = False):
        super().__init__()
        self._meshcat = meshcat
        # Close up, the virtual scene lies among the coils (under the glass): see through them.
        self._coil_opacity = 0.25 if close_view else 1.0
        self._limit_a = device.amplifier.current_limit_a
        self._X_WT = device.tracker.pose_WT()  # the markers come in the tracker's frame T
        n_markers = len(device.instrument_spec().p_IK_m)
        self._currents = self.DeclareVectorInputPort("coil_currents", device.n_coils)
        self._setpoint = self.DeclareVectorInputPort("setpoint", 12)
        self._pose = self.DeclareVectorInputPort("X_WI_measured", 7)
        self._markers = self.DeclareVectorInputPort("markers_measured", 3 * n_markers)
        self._rendered = self.DeclareVectorInputPort("wrench_rendered_W", 6)
        meshcat.SetObject(FORCE_PATH, Cylinder(0.0015, 1.0), Rgba(1.0, 0.55, 0.0, 1.0))
        aim_camera_at_device(meshcat, close=close_view)
        coil = device.coil
        p_WC = device.array.coil_positions_A() + device.p_WA
        for j, p in enumerate(p_WC):
            path = f"{COIL_PATH}/{j}"
            meshcat.SetObject(path, Cylinder(coil.outer_diameter_m / 2, coil.height_m),
                              Rgba(0.6, 0.6, 0.6, 1.0))
            meshcat.SetTransform(path, RigidTransform(p - [0, 0, coil.height_m / 2]))
        for path, opacity in ((SETPOINT_PATH, 0.35), (MEASURED_PATH, 1.0)):
            _add_triad(meshcat, path, length=0.03, radius=0.0012, opacity=opacity)
        for k in range(n_markers):
            meshcat.SetObject(f"{MARKERS_PATH}/{k}", Sphere(0.0025), Rgba(0.1, 0.9, 0.2, 1.0))
        # What the page already shows: a coil's colour or a marker's visibility is sent
        # only when it changes (a steady hover then sends no colours at all), so the
        # loop and a browser rendering in software are not flooded with messages.
        self._shown_steps = np.full((device.n_coils, 4), -1.0)
        self._shown_visible = [None] * n_markers
        # Half a period after MeshcatVisualizer's publishes, so the two frames' costs
        # fall in different 1 ms ticks of a paced run.
        self.DeclarePeriodicPublishEvent(period_s, period_s / 2, self._draw)
        self.DeclareForcedPublishEvent(self._draw)

    def _draw(self, context):
        meshcat = self._meshcat
        colors = current_colors(self._currents.Eval(context), self._limit_a, self._coil_opacity)
        steps = np.round(colors * COLOR_STEPS)
        for j in np.flatnonzero(np.any(steps != self._shown_steps, axis=1)):
            meshcat.SetProperty(f"{COIL_PATH}/{j}", "color", colors[j].tolist())
        self._shown_steps = steps
        setpoint = self._setpoint.Eval(context)
        meshcat.SetTransform(SETPOINT_PATH, RigidTransform(
            RollPitchYaw(setpoint[3:6]), setpoint[0:3]))
        pose = self._pose.Eval(context)
        meshcat.SetTransform(MEASURED_PATH, rigid_transform(pose))
        meshcat.SetTransform(FORCE_PATH, force_rod_transform(
            pose[4:7], self._rendered.Eval(context)[0:3]))
        markers = self._markers.Eval(context).reshape(-1, 3)
        for k, p in enumerate(markers):
            visible = bool(np.all(np.isfinite(p)))
            if visible != self._shown_visible[k]:
                meshcat.SetProperty(f"{MARKERS_PATH}/{k}", "visible", visible)
                self._shown_visible[k] = visible
            if visible:
                meshcat.SetTransform(f"{MARKERS_PATH}/{k}", RigidTransform(self._X_WT @ p))


def force_rod_transform(p_WI, f_W) -> np.ndarray:
    """4x4 transform that stretches a unit cylinder along z into a rod from p_WI (m)
    along f_W (N), FORCE_SCALE_M_PER_N long per newton (zero size when tiny)."""
    length = FORCE_SCALE_M_PER_N * float(np.linalg.norm(f_W))
    if length < FORCE_SCALE_M_PER_N * FORCE_SHOWN_N:
        return np.diag([0.0, 0.0, 0.0, 1.0])
    z = np.asarray(f_W, float) / np.linalg.norm(f_W)
    R = RotationMatrix.MakeFromOneVector(z, 2).matrix()
    X = np.eye(4)
    X[0:3, 0:3] = R @ np.diag([1.0, 1.0, length])
    X[0:3, 3] = np.asarray(p_WI, float) + z * length / 2
    return X


def aim_camera_at_device(meshcat: Meshcat, *, close: bool = False) -> None:
    """Look from the user's side, a little above the glass, at the coil array and the
    instrument over it (the ~0.5 m glass fills the background); hide the metre-scale
    grid and axes and lighten the background so the dark coils and bezel stand out.
    ``close``: nearer, at the handful of centimetres where a virtual scene is touched.

    Publishing a recording resets the view, so runners call this again after it.
    """
    if close:
        meshcat.SetCameraPose(camera_in_world=[0.09, -0.17, 0.09],
                              target_in_world=[0.0, 0.0, -0.01])
    else:
        meshcat.SetCameraPose(camera_in_world=[0.07, -0.17, 0.10],
                              target_in_world=[0.0, 0.0, 0.005])
    meshcat.SetProperty("/Axes", "visible", False)
    meshcat.SetProperty("/Grid", "visible", False)
    meshcat.SetProperty("/Background", "top_color", [0.97, 0.98, 1.0])
    meshcat.SetProperty("/Background", "bottom_color", [0.78, 0.82, 0.88])


def _add_triad(meshcat: Meshcat, path: str, *, length: float, radius: float, opacity: float):
    """Red, green, blue cylinders along x, y, z of the frame at ``path``."""
    axes = (("x", RollPitchYaw(0, np.pi / 2, 0), [length / 2, 0, 0], Rgba(1, 0, 0, opacity)),
            ("y", RollPitchYaw(np.pi / 2, 0, 0), [0, length / 2, 0], Rgba(0, 1, 0, opacity)),
            ("z", RollPitchYaw(0, 0, 0), [0, 0, length / 2], Rgba(0, 0, 1, opacity)))
    for name, rpy, offset, color in axes:
        meshcat.SetObject(f"{path}/{name}", Cylinder(radius, length), color)
        meshcat.SetTransform(f"{path}/{name}", RigidTransform(rpy, offset))
