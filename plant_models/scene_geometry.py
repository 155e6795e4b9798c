"""Solid-body geometry of scene models: principal moments of inertia, the plate
with a hole as boxes, and interpenetration tests of boxes and spheres. Lengths in
m, masses in kg, poses as RigidTransforms in W."""

from typing import NamedTuple, Optional, Sequence

import numpy as np
from pydrake.math import RigidTransform


def box_inertia(mass_kg: float, size_m: Sequence[float]) -> np.ndarray:
    """Principal moments (3,) (kg*m^2) about its centre of a solid box of ``size_m``
    (x, y, z; m)."""
    x2, y2, z2 = np.square(np.asarray(size_m, dtype=float))
    return mass_kg / 12.0 * np.array([y2 + z2, x2 + z2, x2 + y2])


def sphere_inertia(mass_kg: float, radius_m: float) -> np.ndarray:
    """Principal moments (3,) (kg*m^2) of a solid sphere about its centre."""
    return np.full(3, 0.4 * mass_kg * radius_m**2)


def hole_block_boxes(block_size_m, hole_size_m, hole_center_m):
    """The plate with a hole through it as four boxes [(name, centre in W (3,),
    size (3,))] (m), each as thick as the hole is deep: the walls left and right of
    the hole (the plate's full y) and in front of and behind it (between those)."""
    bx, by = block_size_m
    hx, hy, depth = hole_size_m
    cx, cy, top = hole_center_m
    wall_z = top - depth / 2
    side_x = (bx - hx) / 2
    side_y = (by - hy) / 2
    x_wall = (hx + side_x) / 2  # wall centres' distance from the hole's centre (m)
    y_wall = (hy + side_y) / 2
    boxes = [
        ("wall_left", [cx - x_wall, cy, wall_z], [side_x, by, depth]),
        ("wall_right", [cx + x_wall, cy, wall_z], [side_x, by, depth]),
        ("wall_front", [cx, cy - y_wall, wall_z], [hx, side_y, depth]),
        ("wall_back", [cx, cy + y_wall, wall_z], [hx, side_y, depth]),
    ]
    return [(name, np.array(centre), np.array(size)) for name, centre, size in boxes]


def box_overlaps_box(X_WA: RigidTransform, size_A, X_WB: RigidTransform, size_B) -> bool:
    """Whether two solid boxes (full sizes in m, centred on their frames) interpenetrate:
    the separating-axis test over both boxes' face normals and their edges' cross
    products. Boxes that only touch do not overlap."""
    R_A, R_B = X_WA.rotation().matrix(), X_WB.rotation().matrix()
    half_A, half_B = np.asarray(size_A) / 2, np.asarray(size_B) / 2
    p_AB_W = X_WB.translation() - X_WA.translation()
    axes = [R_A[:, i] for i in range(3)] + [R_B[:, j] for j in range(3)]
    axes += [np.cross(R_A[:, i], R_B[:, j]) for i in range(3) for j in range(3)]
    for axis in axes:
        norm = np.linalg.norm(axis)
        if norm < 1e-9:  # parallel edges: their face normals already cover this
            continue
        u = axis / norm
        reach = half_A @ np.abs(R_A.T @ u) + half_B @ np.abs(R_B.T @ u)
        if abs(p_AB_W @ u) >= reach:
            return False
    return True


def sphere_overlaps_box(p_WS, radius_m: float, X_WB: RigidTransform, size_B) -> bool:
    """Whether a solid sphere (centre p_WS, m) and a solid box (full size, m) interpenetrate."""
    p_BS = X_WB.inverse() @ np.asarray(p_WS, dtype=float)
    half = np.asarray(size_B) / 2
    return float(np.linalg.norm(p_BS - np.clip(p_BS, -half, half))) < radius_m


class Solid(NamedTuple):
    """A box of full extents ``size_m`` or, with ``radius_m``, a sphere, centred at X_WS (m)."""

    name: str
    X_WS: RigidTransform
    size_m: Optional[Sequence[float]] = None
    radius_m: Optional[float] = None


def solid_overlaps_box(solid: Solid, box: Solid) -> bool:
    if solid.radius_m is None:
        return box_overlaps_box(solid.X_WS, solid.size_m, box.X_WS, box.size_m)
    return sphere_overlaps_box(solid.X_WS.translation(), solid.radius_m, box.X_WS, box.size_m)


def solid_bottom_z(solid: Solid) -> float:
    """z in W of the solid's lowest point (m)."""
    if solid.radius_m is not None:
        return solid.X_WS.translation()[2] - solid.radius_m
    R_WS = solid.X_WS.rotation().matrix()
    return solid.X_WS.translation()[2] - np.abs(R_WS[2, :]) @ (np.asarray(solid.size_m) / 2)
