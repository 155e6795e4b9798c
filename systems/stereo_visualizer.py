"""Meshcat drawing of the head-tracked stereo view: the user's shutter glasses and
their markers, the two eyes, and each eye's viewing frustum onto the display."""

from __future__ import annotations

import numpy as np
from pydrake.geometry import Box, Meshcat, Rgba, Sphere
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem

from maglev_haptics.systems.rotations import rigid_transform

# Paths below the visualizer's prefix. The glasses, eyes and frusta are groups whose
# objects sit one level down, so hiding a group survives redrawing its objects
# (SetLineSegments replaces the object at its path, properties and all).
GLASSES = "glasses"
EYES = "eyes"
FRUSTA = "frusta"
DISPLAY = "display"
GLASSES_SIZE_M = (0.150, 0.045, 0.015)  # along G's x, y, z (m)
MARKER_RADIUS_M = 0.003  # (m)
EYE_RADIUS_M = 0.006  # (m)
LINE_WIDTH_PX = 2.0  # browsers may draw 1 px whatever is asked (WebGL)
GLASSES_RGBA = Rgba(0.12, 0.12, 0.12, 1.0)
WHITE_RGBA = Rgba(1.0, 1.0, 1.0, 1.0)
LEFT_RGBA = Rgba(0.20, 0.50, 1.00, 1.0)  # blue-ish
RIGHT_RGBA = Rgba(1.00, 0.30, 0.25, 1.0)  # red-ish


def frustum_segments(p_WE, corners_W) -> tuple[np.ndarray, np.ndarray]:
    """(start, end), each (3, 4 n) Fortran-ordered (m, W): a segment from each of the
    n eyes ``p_WE`` ((n, 3) or (3,)) to each of the display's 4 ``corners_W`` ((4, 3)),
    eye by eye, corners in the given order; what ``Meshcat.SetLineSegments`` takes."""
    eyes = np.atleast_2d(np.asarray(p_WE, float))
    corners = _corners(corners_W)
    start = np.repeat(eyes, len(corners), axis=0)
    end = np.tile(corners, (len(eyes), 1))
    return np.asfortranarray(start.T), np.asfortranarray(end.T)


def outline_segments(corners_W) -> tuple[np.ndarray, np.ndarray]:
    """(start, end), each (3, 4) Fortran-ordered (m, W): the closed outline through
    the 4 ``corners_W`` ((4, 3)) in their order, last corner back to the first."""
    corners = _corners(corners_W)
    return (np.asfortranarray(corners.T),
            np.asfortranarray(np.roll(corners, -1, axis=0).T))


def _corners(corners_W) -> np.ndarray:
    corners = np.asarray(corners_W, float)
    if corners.shape != (4, 3):
        raise ValueError(f"display corners must be (4, 3), got {corners.shape}")
    return corners


class StereoVisualizer(LeafSystem):
    """Draws the stereo view's geometry at ``period_s`` and on ForcedPublish.

    .. pydrake_system::

        name: StereoVisualizer
        input_ports:
        - X_WG
        - eye_positions_W

    ``X_WG`` [qw, qx, qy, qz, x, y, z] (m): the glasses pose the views are computed
    from; ``eye_positions_W`` [left xyz, right xyz] (m). The glasses are a dark
    150 x 45 x 15 mm box at G's origin with white spheres at their markers; the eyes
    are spheres, left blue, right red, each with the four edges of its viewing frustum
    to the display's corners in its colour; the display's active area is outlined in
    white. A non-finite input (the head tracker lost the glasses) hides what is drawn
    from it until it is finite again. Like the device overlays these are drawn live
    only: a Meshcat recording replays transforms, not line segments.
    """

    def __init__(self, *, meshcat: Meshcat, display_corners_W, p_GK_m,
                 period_s: float = 1 / 30, prefix: str = "/stereo"):
        """``display_corners_W`` (4, 3): the active area's corners in W, lower-left,
        lower-right, upper-right, upper-left (m); ``p_GK_m`` (n, 3): the glasses'
        markers in G (m)."""
        super().__init__()
        self._meshcat = meshcat
        self._corners = _corners(display_corners_W).copy()
        p_GK = np.asarray(p_GK_m, float).reshape(-1, 3)
        self._glasses = f"{prefix}/{GLASSES}"
        self._eyes = f"{prefix}/{EYES}"
        self._frusta = f"{prefix}/{FRUSTA}"
        self._X_WG = self.DeclareVectorInputPort("X_WG", 7)
        self._eye_positions = self.DeclareVectorInputPort("eye_positions_W", 6)
        meshcat.SetObject(f"{self._glasses}/frame", Box(*GLASSES_SIZE_M), GLASSES_RGBA)
        for k, p in enumerate(p_GK):
            path = f"{self._glasses}/markers/{k}"
            meshcat.SetObject(path, Sphere(MARKER_RADIUS_M), WHITE_RGBA)
            meshcat.SetTransform(path, RigidTransform(p))
        meshcat.SetObject(f"{self._eyes}/left", Sphere(EYE_RADIUS_M), LEFT_RGBA)
        meshcat.SetObject(f"{self._eyes}/right", Sphere(EYE_RADIUS_M), RIGHT_RGBA)
        meshcat.SetLineSegments(f"{prefix}/{DISPLAY}", *outline_segments(self._corners),
                                LINE_WIDTH_PX, WHITE_RGBA)
        # Hidden until the first finite input: not piled up at W's origin before it.
        for path in (self._glasses, self._eyes, self._frusta):
            meshcat.SetProperty(path, "visible", False)
        self.DeclarePeriodicPublishEvent(period_s, 0.0, self._draw)
        self.DeclareForcedPublishEvent(self._draw)

    def _draw(self, context):
        meshcat = self._meshcat
        X_WG = self._X_WG.Eval(context)
        glasses_seen = bool(np.all(np.isfinite(X_WG)))
        meshcat.SetProperty(self._glasses, "visible", glasses_seen)
        if glasses_seen:
            meshcat.SetTransform(self._glasses, rigid_transform(X_WG))
        eyes = self._eye_positions.Eval(context).reshape(2, 3)
        eyes_seen = bool(np.all(np.isfinite(eyes)))
        meshcat.SetProperty(self._eyes, "visible", eyes_seen)
        meshcat.SetProperty(self._frusta, "visible", eyes_seen)
        if not eyes_seen:
            return
        meshcat.SetTransform(f"{self._eyes}/left", RigidTransform(eyes[0]))
        meshcat.SetTransform(f"{self._eyes}/right", RigidTransform(eyes[1]))
        for name, p_WE, rgba in (("left", eyes[0], LEFT_RGBA), ("right", eyes[1], RIGHT_RGBA)):
            meshcat.SetLineSegments(f"{self._frusta}/{name}",
                                    *frustum_segments(p_WE, self._corners),
                                    LINE_WIDTH_PX, rgba)
