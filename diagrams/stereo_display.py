"""The co-located stereo display in the diagram: its scenario schema and builder.

The station (``diagrams/station.py``) holds the user's scripted head and the head
sensor; the application, built here, holds the head pose predictor, the per-eye
views at the display's refresh rate, the rendered frames at ``images.rate_hz``
and the Meshcat drawing of the glasses and the frusta.
"""

from dataclasses import dataclass, field
from typing import List, Optional

from pydrake.systems.framework import DiagramBuilder

from maglev_haptics.diagrams.head_script import HeadScript
from maglev_haptics.hardware.config_checks import nonnegative, positive, require, vector
from maglev_haptics.systems.head_predictor import (
    HeadPosePredictor, HeadPredictorConfig)
from maglev_haptics.systems.head_sensor import HeadOcclusion
from maglev_haptics.systems.stereo import (
    StereoView, check_clipping, check_ipd, display_rectangle)
from maglev_haptics.systems.stereo_renderer import StereoRenderer
from maglev_haptics.systems.stereo_visualizer import StereoVisualizer

ENCODERS = ("auto", "png")


@dataclass
class StereoImages:
    """Rendered eye images, written as side-by-side and anaglyph video."""

    rate_hz: float = 30.0  # frames a second; 0: views only, no images
    size_px: List[int] = field(default_factory=lambda: [560, 350])  # per eye: a third of the panel
    encoder: str = "auto"  # auto: MP4 where ffmpeg runs, else PNG sequences; png: always PNGs
    # In real-time runs frames are skipped while rendering has taken more than this
    # share of the wall clock; offline runs render every frame.
    realtime_wall_share: float = 0.3


@dataclass
class StereoConfig:
    head: HeadScript = field(default_factory=HeadScript)
    predictor: HeadPredictorConfig = field(default_factory=HeadPredictorConfig)
    occlusions: List[HeadOcclusion] = field(default_factory=list)  # the glasses unseen
    view_rate_hz: Optional[float] = None  # None: the display's refresh rate (Hz)
    near_m: float = 0.05  # clipping planes, from the eye along the screen normal (m)
    far_m: float = 2.0
    images: StereoImages = field(default_factory=StereoImages)
    # Virtual points whose co-location error is reported (m, W); default: the centre of
    # the paper's ball, 2 cm in diameter and 4 cm below the display.
    colocation_points_m: List[List[float]] = field(default_factory=lambda: [[0.0, 0.0, -0.04]])

    def validate(self, path: str, device, device_path: str = "device") -> None:
        """Range checks of the display and its devices; a ValueError names the field (under
        ``path``, or ``device_path`` for ``device``'s), its value and what is allowed."""
        screen = display_rectangle(device.display)
        positive(f"{device_path}.display.refresh_hz", device.display.refresh_hz)
        vector(f"{device_path}.display.pose_W", device.display.pose_W, 6)
        check_ipd(device.glasses.ipd_m, f"{device_path}.glasses.ipd_m")
        t = device.head_tracker
        positive(f"{device_path}.head_tracker.rate_hz", t.rate_hz)
        nonnegative(f"{device_path}.head_tracker.noise_m", t.noise_m)
        nonnegative(f"{device_path}.head_tracker.latency_s", t.latency_s)
        markers = device.glasses.p_GK_m
        require(isinstance(markers, list) and len(markers) >= 3, f"{device_path}.glasses.p_GK_m",
                markers, "needs at least 3 markers for the tracker's pose fit")
        for i, marker in enumerate(markers):
            vector(f"{device_path}.glasses.p_GK_m[{i}]", marker, 3)
        self.head.validate(f"{path}.head", screen=screen, ipd_m=device.glasses.ipd_m)
        self.predictor.validate(f"{path}.predictor", head_tracker_rate_hz=t.rate_hz)
        for i, o in enumerate(self.occlusions):
            require(0 <= o.start_s <= o.end_s, f"{path}.occlusions[{i}]", (o.start_s, o.end_s),
                    "needs 0 <= start_s <= end_s")
        if self.view_rate_hz is not None:
            positive(f"{path}.view_rate_hz", self.view_rate_hz)
        check_clipping(self.near_m, self.far_m, f"{path}.near_m, far_m")
        i = self.images
        nonnegative(f"{path}.images.rate_hz", i.rate_hz)
        require(isinstance(i.size_px, list) and len(i.size_px) == 2
                and all(isinstance(v, int) and 2 <= v <= 4096 for v in i.size_px),
                f"{path}.images.size_px", i.size_px, "must be [width, height], integers 2-4096")
        require(i.encoder in ENCODERS, f"{path}.images.encoder", i.encoder,
                f"must be one of {', '.join(ENCODERS)}")
        require(0 < i.realtime_wall_share <= 1, f"{path}.images.realtime_wall_share",
                i.realtime_wall_share, "must be in (0, 1]")
        for k, point in enumerate(self.colocation_points_m):
            vector(f"{path}.colocation_points_m[{k}]", point, 3)


def view_period_s(stereo: StereoConfig, display) -> float:
    return 1.0 / (stereo.view_rate_hz if stereo.view_rate_hz is not None else display.refresh_hz)


@dataclass
class StereoParts:
    predictor: HeadPosePredictor
    view: StereoView
    renderer: Optional[StereoRenderer]
    visualizer: Optional[StereoVisualizer] = None


def AddStereoDisplay(builder: DiagramBuilder, *, scenario, station, query_object_port,
                     frame_period_s: float, meshcat=None, frame_sink=None,
                     realtime: bool = False, surface=None) -> StereoParts:
    """Predictor, views and (given a ``frame_sink(t, left, right)`` and images on)
    the renderer of the virtual world behind ``query_object_port`` (its SceneGraph
    must have the stereo renderer, ``AddStereoRenderer``). ``surface``: a
    (SurfaceLayer, output port of its vertex positions) drawn over that world.
    With ``meshcat``, the glasses and frusta are drawn every ``frame_period_s`` (s)."""
    stereo, device = scenario.stereo, scenario.device
    period_s = view_period_s(stereo, device.display)
    screen = display_rectangle(device.display)
    predictor = builder.AddNamedSystem("head_pose_predictor", HeadPosePredictor(
        config=stereo.predictor, tracker_rate_hz=device.head_tracker.rate_hz, period_s=period_s))
    view = builder.AddNamedSystem("stereo_view", StereoView(
        screen=screen, ipd_m=device.glasses.ipd_m, period_s=period_s,
        near_m=stereo.near_m, far_m=stereo.far_m))
    builder.Connect(station.GetOutputPort("glasses_measured"),
                    predictor.GetInputPort("glasses_measured"))
    builder.Connect(predictor.GetOutputPort("X_WG_predicted"), view.GetInputPort("X_WG"))
    renderer = None
    if frame_sink is not None and stereo.images.rate_hz > 0:
        renderer = builder.AddNamedSystem("stereo_renderer", StereoRenderer(
            rate_hz=stereo.images.rate_hz, image_px=stereo.images.size_px,
            display_px=(screen.width_px, screen.height_px), near_m=stereo.near_m,
            far_m=stereo.far_m, sink=frame_sink,
            max_wall_share=stereo.images.realtime_wall_share if realtime else None,
            surface=surface[0] if surface is not None else None))
        builder.Connect(query_object_port, renderer.GetInputPort("query_object"))
        if surface is not None:
            builder.Connect(surface[1], renderer.GetInputPort("surface_positions_m"))
        for name in ("camera_left", "camera_right", "view_ok"):
            builder.Connect(view.GetOutputPort(name), renderer.GetInputPort(name))
    visualizer = None
    if meshcat is not None:
        visualizer = builder.AddNamedSystem("stereo_visualizer", StereoVisualizer(
            meshcat=meshcat, display_corners_W=screen.corners_W,
            p_GK_m=device.glasses.p_GK_m, period_s=frame_period_s))
        builder.Connect(predictor.GetOutputPort("X_WG_predicted"),
                        visualizer.GetInputPort("X_WG"))
        builder.Connect(view.GetOutputPort("eye_positions_W"),
                        visualizer.GetInputPort("eye_positions_W"))
    return StereoParts(predictor=predictor, view=view, renderer=renderer, visualizer=visualizer)
