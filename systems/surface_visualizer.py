"""Meshcat drawing of a deformable body's surface (the lattice's top, or a
tissue's boundary) as a triangle mesh, and the contact force on the probe as a rod."""

from __future__ import annotations

import numpy as np
from pydrake.geometry import Cylinder, Meshcat, Rgba
from pydrake.math import RotationMatrix
from pydrake.systems.framework import LeafSystem

from maglev_haptics.systems.rotations import rigid_transform

SURFACE_PATH = "/deformable_surface/top"  # the lattice's; a tissue's under /tissue/<name>
WIRE_PATH = "/deformable_surface/wire"
FORCE_PATH = "/deformable_surface/contact_force"
# Opaque: three.js draws see-through objects far to near by their origin, and the
# translucent display glass, whose centre is farther than W's origin (the mesh's),
# would be drawn first and hide a see-through surface under it. The wireframe
# shows the shape, which the shading alone leaves flat from most angles.
JELLY_RGBA = Rgba(0.40, 0.85, 0.30, 1.0)  # lime jelly
WIRE_RGBA = Rgba(0.10, 0.35, 0.10, 1.0)


def wire_rgba_of(rgba: Rgba) -> Rgba:
    """A wireframe's colour over a surface of ``rgba``: the same hue, darker."""
    return Rgba(0.3 * rgba.r(), 0.3 * rgba.g(), 0.3 * rgba.b(), 1.0)
FORCE_RGBA = Rgba(0.95, 0.10, 0.65, 1.0)  # magenta, apart from the device's orange rod
FORCE_ROD_RADIUS_M = 0.002  # (m): sheathes the probe's 1.5 mm shaft, inside its tip
FORCE_SCALE_M_PER_N = 0.1  # rod length per newton of contact force (m/N)
FORCE_SHOWN_N = 0.005  # smaller contact forces are not drawn (N)
# From the surface's centre to the camera (m, W axes): the default 80 x 60 mm surface
# whole, from the user's right, low enough to see the probe sink in.
CAMERA_OFFSET_M = (0.038, -0.063, 0.029)


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
    """4x4 transform stretching a unit cylinder along z into a rod along the force f_W
    (N) on the probe sphere (centre p_WP, radius ``radius_m``, m), ``scale_m_per_n``
    long per newton, from the sphere's contact side: its point facing away from f_W.
    Zero size below ``shown_n``."""
    magnitude = float(np.linalg.norm(f_W))
    if magnitude < shown_n:
        return np.diag([0.0, 0.0, 0.0, 1.0])
    z = np.asarray(f_W, float) / magnitude
    length = scale_m_per_n * magnitude
    X = np.eye(4)
    X[0:3, 0:3] = RotationMatrix.MakeFromOneVector(z, 2).matrix() @ np.diag([1.0, 1.0, length])
    X[0:3, 3] = np.asarray(p_WP, float) + z * (length / 2 - radius_m)
    return X


class SurfaceVisualizer(LeafSystem):
    """Draws a deformable surface and its contact force at ``period_s`` and on
    ForcedPublish.

    .. pydrake_system::

        name: SurfaceVisualizer
        input_ports:
        - surface_positions_m
        - X_WT
        - wrench_on_tool_W

    ``surface_positions_m`` (3 n_s): the surface vertices in W (m), the rows
    ``faces`` index; ``X_WT`` [qw, qx, qy, qz, x, y, z] the tool pose;
    ``wrench_on_tool_W`` [f; tau] (N, N*m) the contact's wrench on the tool. The
    surface is a triangle mesh in ``rgba`` with a wireframe over it, both resent
    whole each frame (Meshcat has no vertex update); the force is a magenta rod
    from the probe's contact side along the force, FORCE_SCALE_M_PER_N long per
    newton. Like the device overlays these are drawn live only: a Meshcat recording
    replays transforms, not meshes.
    """

    def __init__(self, *, meshcat: Meshcat, faces: np.ndarray, num_vertices: int, p_TP_m,
                 probe_radius_m: float, rgba: Rgba = JELLY_RGBA,
                 wire_rgba: Rgba = WIRE_RGBA, path: str = "/deformable_surface", camera_target_m=None,
                 period_s: float = 1 / 30):
        """``faces`` (3, T) int32 Fortran-ordered (``surface_faces``) index the
        ``num_vertices`` surface vertices; ``p_TP_m`` (3,): the probe sphere's centre
        in the tool frame T (m); ``path``: the Meshcat folder of the surface, its
        wireframe and the force rod; ``camera_target_m`` (3,) in W (m): look at it
        from CAMERA_OFFSET_M rather than at the device."""
        super().__init__()
        self._meshcat = meshcat
        self._p_TP = np.asarray(p_TP_m, float).copy()
        self._radius_m = float(probe_radius_m)
        self._faces = faces
        self._rgba = rgba
        self._wire_rgba = wire_rgba
        self._paths = (f"{path}/top", f"{path}/wire", f"{path}/contact_force")
        self._positions = self.DeclareVectorInputPort("surface_positions_m", 3 * num_vertices)
        self._X_WT = self.DeclareVectorInputPort("X_WT", 7)
        self._wrench = self.DeclareVectorInputPort("wrench_on_tool_W", 6)
        meshcat.SetObject(self._paths[2], Cylinder(FORCE_ROD_RADIUS_M, 1.0), FORCE_RGBA)
        meshcat.SetTransform(self._paths[2], np.diag([0.0, 0.0, 0.0, 1.0]))
        if camera_target_m is not None:
            meshcat.SetCameraPose(camera_in_world=np.add(camera_target_m, CAMERA_OFFSET_M),
                                  target_in_world=list(camera_target_m))
        self.DeclarePeriodicPublishEvent(period_s, 0.0, self._draw)
        self.DeclareForcedPublishEvent(self._draw)

    def _draw(self, context):
        # (3 n_s,) vertex by vertex, C order: its (n_s, 3) transpose is Fortran (3, n_s).
        vertices = self._positions.Eval(context).reshape(-1, 3).T
        surface, wire, force = self._paths
        self._meshcat.SetTriangleMesh(surface, vertices, self._faces, self._rgba)
        self._meshcat.SetTriangleMesh(wire, vertices, self._faces, self._wire_rgba,
                                      wireframe=True)
        p_WP = rigid_transform(self._X_WT.Eval(context)) @ self._p_TP
        self._meshcat.SetTransform(force, force_rod_transform(
            p_WP, self._radius_m, self._wrench.Eval(context)[0:3]))
