"""Meshcat drawing of the deformable surface: the lattice's top surface as a
triangle mesh, and the contact force on the tool as a rod from the probe."""

from __future__ import annotations

import numpy as np
from pydrake.geometry import Cylinder, Meshcat, Rgba
from pydrake.math import RotationMatrix
from pydrake.systems.framework import LeafSystem

from maglev_haptics.systems.rotations import rotation_from_quaternion

SURFACE_PATH = "/deformable_surface/top"
WIRE_PATH = "/deformable_surface/wire"
FORCE_PATH = "/deformable_surface/contact_force"
# Lime jelly, see-through enough to show the force rod in it; the darker wireframe
# shows the surface's shape, which shading alone leaves flat from most angles.
JELLY_RGBA = Rgba(0.30, 0.80, 0.25, 0.8)
WIRE_RGBA = Rgba(0.10, 0.35, 0.10, 0.5)
FORCE_RGBA = Rgba(1.0, 0.55, 0.0, 1.0)  # orange, as the device's rendered-force rod
FORCE_ROD_RADIUS_M = 0.0008  # (m), thinner than the probe's 1.5 mm shaft
FORCE_SCALE_M_PER_N = 0.1  # rod length per newton of contact force (m/N)
FORCE_SHOWN_N = 0.005  # smaller contact forces are not drawn (N)
# Looks at the default 80 x 60 mm surface (15 mm under the display) from the user's
# side, high enough to see the dent under the probe (m, in W).
CAMERA_IN_WORLD_M = (0.03, -0.11, 0.07)
CAMERA_TARGET_M = (0.0, 0.0, -0.015)


def surface_faces(surface: np.ndarray, surface_triangles: np.ndarray) -> np.ndarray:
    """(3, T) int32 Fortran-ordered faces indexing the surface vertices in the order of
    ``surface.ravel()`` (the rows of ``surface_positions_m``), from ``surface_triangles``
    (T, 3) of mass indices; what ``Meshcat.SetTriangleMesh`` takes."""
    surface = np.asarray(surface).ravel()
    row = np.full(int(surface.max()) + 1, -1, dtype=np.int64)
    row[surface] = np.arange(len(surface))
    triangles = np.asarray(surface_triangles)
    if triangles.size and (triangles.max() >= len(row) or np.any(row[triangles] < 0)):
        raise ValueError("surface_triangles index a mass that is not a surface vertex")
    return np.asfortranarray(row[triangles].T.astype(np.int32))


def force_rod_transform(p_WP, radius_m: float, f_W, scale_m_per_n: float = FORCE_SCALE_M_PER_N,
                        shown_n: float = FORCE_SHOWN_N) -> np.ndarray:
    """4x4 transform stretching a unit cylinder along z into a rod along f_W (N),
    ``scale_m_per_n`` long per newton, ending where it pushes: at the point of the
    probe sphere (centre p_WP, radius ``radius_m``, m) facing away from f_W, its
    contact side. The rod then lies in the surface, off the tool's shaft (a force
    mostly along the shaft would hide in it). Zero size below ``shown_n``."""
    magnitude = float(np.linalg.norm(f_W))
    if magnitude < shown_n:
        return np.diag([0.0, 0.0, 0.0, 1.0])
    z = np.asarray(f_W, float) / magnitude
    length = scale_m_per_n * magnitude
    X = np.eye(4)
    X[0:3, 0:3] = RotationMatrix.MakeFromOneVector(z, 2).matrix() @ np.diag([1.0, 1.0, length])
    X[0:3, 3] = np.asarray(p_WP, float) - z * (radius_m + length / 2)
    return X


class LatticeVisualizer(LeafSystem):
    """Draws the deformable surface and its contact force at ``period_s`` and on
    ForcedPublish.

    .. pydrake_system::

        name: LatticeVisualizer
        input_ports:
        - surface_positions_m
        - X_WT
        - wrench_on_tool_W

    ``surface_positions_m`` (3 n_s): the surface vertices in W (m), in the order of
    ``lattice.surface.ravel()``; ``X_WT`` [qw, qx, qy, qz, x, y, z] the tool pose;
    ``wrench_on_tool_W`` [f; tau] (N, N*m) the contact's wrench on the tool. The top
    surface is a translucent triangle mesh resent whole each frame (Meshcat has no
    vertex update); the force is an orange rod from the probe's contact side,
    FORCE_SCALE_M_PER_N long per newton. Like the device overlays these are drawn
    live only: a Meshcat recording replays transforms, not meshes.
    """

    def __init__(self, *, meshcat: Meshcat, lattice, p_TP_m, probe_radius_m: float,
                 period_s: float = 1 / 30, aim_camera: bool = True):
        """``p_TP_m`` (3,): the probe sphere's centre in the tool frame T (m);
        ``aim_camera``: look at the surface rather than the device."""
        super().__init__()
        self._meshcat = meshcat
        self._p_TP = np.asarray(p_TP_m, float).copy()
        self._radius_m = float(probe_radius_m)
        self._faces = surface_faces(lattice.surface, lattice.surface_triangles)
        n_s = lattice.surface.size
        self._positions = self.DeclareVectorInputPort("surface_positions_m", 3 * n_s)
        self._X_WT = self.DeclareVectorInputPort("X_WT", 7)
        self._wrench = self.DeclareVectorInputPort("wrench_on_tool_W", 6)
        # The rest shape, until the first publish sends the state's.
        self._draw_surface(lattice.positions_m[lattice.surface.ravel()].ravel())
        meshcat.SetObject(FORCE_PATH, Cylinder(FORCE_ROD_RADIUS_M, 1.0), FORCE_RGBA)
        meshcat.SetTransform(FORCE_PATH, np.diag([0.0, 0.0, 0.0, 1.0]))
        if aim_camera:
            meshcat.SetCameraPose(camera_in_world=list(CAMERA_IN_WORLD_M),
                                  target_in_world=list(CAMERA_TARGET_M))
        self.DeclarePeriodicPublishEvent(period_s, 0.0, self._draw)
        self.DeclareForcedPublishEvent(self._draw)

    def _draw_surface(self, positions_m):
        # (3 n_s,) vertex by vertex, C order: its (n_s, 3) transpose is Fortran (3, n_s).
        vertices = np.asarray(positions_m, float).reshape(-1, 3).T
        self._meshcat.SetTriangleMesh(SURFACE_PATH, vertices, self._faces, JELLY_RGBA)
        self._meshcat.SetTriangleMesh(WIRE_PATH, vertices, self._faces, WIRE_RGBA,
                                      wireframe=True)

    def _draw(self, context):
        self._draw_surface(self._positions.Eval(context))
        X_WT = self._X_WT.Eval(context)
        p_WP = X_WT[4:7] + rotation_from_quaternion(X_WT[0:4]) @ self._p_TP
        self._meshcat.SetTransform(FORCE_PATH, force_rod_transform(
            p_WP, self._radius_m, self._wrench.Eval(context)[0:3]))
