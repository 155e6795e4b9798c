"""The scenario's schema, its range checks, and loading a named scenario.

A scenario file holds several named scenarios (plus an optional ``Defaults``
entry that is ignored); each is a :class:`Scenario` in YAML, loaded with
``pydrake.common.yaml.yaml_load_typed`` over the defaults, so every field can
be left out. What Drake's loader refuses (unknown keys, wrong types, unknown
tags) is explained field by field in ``diagrams/scenario_diagnosis.py``. After
loading, the values are range-checked, each error naming the field, its value
and what is allowed.
"""

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Union

from pydrake.common.yaml import yaml_dump, yaml_dump_typed, yaml_load_typed
from pydrake.multibody.plant import MultibodyPlantConfig

from maglev_haptics.diagrams.deformable_scene import DeformableSurface
from maglev_haptics.diagrams.hand_script import MeshcatHand, ScriptedHand
from maglev_haptics.diagrams.lcm_station import DEVICE_TRUTH_FIELDS, LcmStation, SimStation
from maglev_haptics.diagrams.scenario_diagnosis import load_typed, parse_mapping
from maglev_haptics.diagrams.scenario_files import (  # noqa: F401  (the light half, re-exported)
    LONGEST_S, SCENARIO_DIR, ScenarioError, read_text_file, resolve_scenario_file,
    scenario_names, shipped_scenario_files)
from maglev_haptics.diagrams.scene import HERE, HangingBall, ModelScene, PaddleBall, PegInHole
from maglev_haptics.diagrams.scene_models import check_model_scene, resolve_here
from maglev_haptics.diagrams.stereo_display import StereoConfig
from maglev_haptics.diagrams.waypoints import Waypoint
from maglev_haptics.hardware.config_checks import nonnegative, positive, require, vector
from maglev_haptics.hardware.device import DeviceConfig
from maglev_haptics.systems.device_supervisor import WatchdogConfig
from maglev_haptics.systems.haptic_coupling import CouplingConfig
from maglev_haptics.systems.haptic_supervisor import SupervisorConfig
from maglev_haptics.systems.heightmap import ImageHeightmap
from maglev_haptics.systems.levitation_controller import ControllerConfig
from maglev_haptics.systems.marker_sensor import Occlusion
from maglev_haptics.systems.fault_injection import (
    CorruptSample, LatencySpike, Shove, StuckAmplifier)
from maglev_haptics.systems.pose_estimator import PoseEstimatorConfig

HIGHEST_RATE_HZ = 1e5  # the loop's, the log's and the trackers' rates at most (Hz)
HIGHEST_DAMPING_RATIO = 100.0  # the controller's, at most (past it, the gains overflow)
LONGEST_PLANT_STEP_S = 0.1  # the station plant's time step at most (s)


def check_script_length(steps) -> None:
    """``steps``, a script's (field path, seconds) in the order they add up: a
    ValueError naming the field that takes the script past LONGEST_S (a huge value
    would overflow its tables, or vanish in a float sum)."""
    total_s = 0.0
    for path, seconds in steps:
        total_s += seconds
        require(total_s <= LONGEST_S, path, seconds,
                f"takes its script to {total_s:.6g} s; a script lasts at most {LONGEST_S:g} s")


@dataclass
class CalibrationFlight:
    """A flight of ``maglev calibrate plan``: its log keeps what a fit reads (the
    tracker's samples as the station gives them, ``markers_measured`` in the tracker's
    frame and ``markers_sample_time_s``), and the instrument may carry a known payload
    (hung by the user; added by a simulated station)."""

    flight: str = ""  # the plan's name for it (registration, holds, steps, payload)
    payload_kg: float = 0.0  # a known mass hung on the instrument (kg)
    payload_p_I_m: List[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])  # where, in I (m)

    def validate(self, path: str, device: DeviceConfig) -> None:
        mass_kg = device.instrument_spec().mass_kg
        require(0.0 <= self.payload_kg <= 0.5 * mass_kg, f"{path}.payload_kg", self.payload_kg,
                f"must be between 0 and half the instrument's mass ({0.5 * mass_kg:g} kg)")
        vector(f"{path}.payload_p_I_m", self.payload_p_I_m, 3)


@dataclass
class MotionScript:
    """Rest on the glass, ramp the force up, fly the waypoints, land, ramp down."""

    start_xy_yaw: List[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])  # rest place (m, m, rad)
    takeoff_at_s: float = 0.2  # the safe force ramp starts here (s)
    force_ramp_s: float = 0.2  # duration of the force ramps at takeoff and after landing (s)
    waypoints: List[Waypoint] = field(default_factory=lambda: [Waypoint()])
    landing_s: float = 1.5  # minimum-jerk descent onto the glass, after levelling out as long if tilted (s)
    settle_s: float = 0.3  # time on the glass, still levitation-controlled, before ramp-down (s)

    def validate(self, path: str = "motion") -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        vector(f"{path}.start_xy_yaw", self.start_xy_yaw, 3)
        positive(f"{path}.takeoff_at_s", self.takeoff_at_s)
        for name in ("force_ramp_s", "landing_s"):
            positive(f"{path}.{name}", getattr(self, name))
        nonnegative(f"{path}.settle_s", self.settle_s)
        require(len(self.waypoints) > 0, f"{path}.waypoints", self.waypoints,
                "must hold at least one pose to hover at")
        for i, w in enumerate(self.waypoints):
            vector(f"{path}.waypoints[{i}].pose", w.pose, 6)
            positive(f"{path}.waypoints[{i}].move_s", w.move_s)
            nonnegative(f"{path}.waypoints[{i}].hold_s", w.hold_s)
        steps = [(f"{path}.takeoff_at_s", self.takeoff_at_s),
                 (f"{path}.force_ramp_s", self.force_ramp_s)]
        for i, w in enumerate(self.waypoints):
            steps += [(f"{path}.waypoints[{i}].move_s", w.move_s),
                      (f"{path}.waypoints[{i}].hold_s", w.hold_s)]
        # The landing levels out first, as long, when tilted; then it settles and ramps down.
        steps += [(f"{path}.landing_s", 2 * self.landing_s), (f"{path}.settle_s", self.settle_s),
                  (f"{path}.force_ramp_s", self.force_ramp_s)]
        check_script_length(steps)


@dataclass
class Haptics:
    """The virtual scene, the coupling that lets the user feel it, and when it is on.

    Haptics is requested from ``enable_at_s`` and engages once the handle is
    gripped; it is requested until ``disable_at_s`` (null: until the motion script's
    landing begins, after its last hold).
    """

    scene: Union[PegInHole, HangingBall, PaddleBall, ModelScene, DeformableSurface] = field(
        default_factory=PegInHole)
    coupling: CouplingConfig = field(default_factory=CouplingConfig)
    supervisor: SupervisorConfig = field(default_factory=SupervisorConfig)
    enable_at_s: float = 2.0  # (s)
    disable_at_s: Optional[float] = None  # (s)
    # A rigid scene's plant steps in a worker process on the other core ("worker"),
    # bit for bit as in this diagram ("in_place", which the loop's linearization needs).
    scene_stepping: str = "worker"

    def validate(self, path: str = "haptics") -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        self.scene.validate(f"{path}.scene")
        if isinstance(self.scene, ModelScene):
            check_model_scene(self.scene, f"{path}.scene")
        require(self.scene_stepping in ("worker", "in_place"), f"{path}.scene_stepping",
                self.scene_stepping, "one of worker, in_place")
        nonnegative(f"{path}.enable_at_s", self.enable_at_s)
        if self.disable_at_s is not None:
            require(isinstance(self.disable_at_s, (int, float))
                    and self.disable_at_s > self.enable_at_s, f"{path}.disable_at_s",
                    self.disable_at_s, f"must be after enable_at_s ({self.enable_at_s} s), or null")
        self.coupling.validate(f"{path}.coupling")
        self.supervisor.validate(f"{path}.supervisor")


@dataclass
class Scenario:
    device: DeviceConfig = field(default_factory=DeviceConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    estimator: PoseEstimatorConfig = field(default_factory=PoseEstimatorConfig)
    motion: MotionScript = field(default_factory=MotionScript)
    occlusions: List[Occlusion] = field(default_factory=list)  # marker null: all (instrument lost)
    marker_dropout_probability: float = 0.0  # per marker and sample
    control_rate_hz: float = 1000.0  # controller, allocator, amplifiers (860: synchronous with the tracker)
    log_rate_hz: float = 1000.0
    # The station's plant: the instrument and the glass, point contact (its cost a
    # step: `maglev bench`, "plant step"). Unsampled output ports: the plant then
    # steps in the same discrete update as the loop instead of an unrestricted update
    # before it, so the loop's cached values are computed once a tick (and the
    # plant linearizes: a sampled output would linearize to the identity).
    plant_config: MultibodyPlantConfig = field(default_factory=lambda: MultibodyPlantConfig(
        time_step=1e-3, discrete_contact_approximation="lagged",
        use_sampled_output_ports=False))
    # The simulated user's hand (station), scripted or driven from Meshcat; null: none.
    hand: Optional[Union[ScriptedHand, MeshcatHand]] = None
    haptics: Optional[Haptics] = None  # null: levitation only
    # The head-tracked stereo display; null: none (``maglev run --stereo`` turns it on).
    stereo: Optional[StereoConfig] = None
    duration_s: Optional[float] = None  # None: the motion script's length
    random_seed: int = 0
    # The station: simulated in this diagram, or whatever answers on LCM
    # (``maglev device-sim`` or a lab's drivers; diagrams/lcm_station.py).
    station: Union[SimStation, LcmStation] = field(default_factory=SimStation)
    # A flight of ``maglev calibrate plan``; null: an ordinary run.
    calibration: Optional[CalibrationFlight] = None
    # The device supervisor's watchdogs (systems/device_supervisor.py).
    watchdog: WatchdogConfig = field(default_factory=WatchdogConfig)
    # Faults injected into the simulated station (systems/fault_injection.py).
    faults: List[Union[LatencySpike, CorruptSample, StuckAmplifier, Shove]] = field(
        default_factory=list)

    def validate(self, label: str) -> None:
        """Range checks of every config, each error naming ``label: path.field``, its
        value and what is allowed; then the checks across configs."""
        # The rates first: the checks below divide by them.
        positive(f"{label}: control_rate_hz", self.control_rate_hz)
        positive(f"{label}: log_rate_hz", self.log_rate_hz)
        positive(f"{label}: plant_config.time_step", self.plant_config.time_step)
        self.device.validate(f"{label}: device")
        for tracker in ("tracker", "head_tracker"):
            rate_hz = getattr(self.device, tracker).rate_hz
            require(rate_hz <= HIGHEST_RATE_HZ, f"{label}: device.{tracker}.rate_hz", rate_hz,
                    f"must be at most {HIGHEST_RATE_HZ:g} Hz")
        self.controller.validate(f"{label}: controller")
        nyquist_hz = self.control_rate_hz / 2
        for i, natural_hz in enumerate(self.controller.natural_frequency_hz):
            require(natural_hz < nyquist_hz, f"{label}: controller.natural_frequency_hz[{i}]",
                    natural_hz, f"must be below half the control rate ({nyquist_hz:g} Hz)")
        for i, ratio in enumerate(self.controller.damping_ratio):
            require(ratio <= HIGHEST_DAMPING_RATIO, f"{label}: controller.damping_ratio[{i}]",
                    ratio, f"must be at most {HIGHEST_DAMPING_RATIO:g}")
        require(self.plant_config.time_step <= LONGEST_PLANT_STEP_S,
                f"{label}: plant_config.time_step", self.plant_config.time_step,
                f"must be at most {LONGEST_PLANT_STEP_S:g} s")
        self.motion.validate(f"{label}: motion")
        self.watchdog.validate(f"{label}: watchdog")
        n_markers = len(self.device.instrument_spec().p_IK_m)
        for i, o in enumerate(self.occlusions):
            require(o.marker is None or 0 <= o.marker < n_markers,
                    f"{label}: occlusions[{i}].marker", o.marker,
                    f"must be null (all markers) or a marker index 0..{n_markers - 1}")
            require(0 <= o.start_s <= o.end_s, f"{label}: occlusions[{i}]",
                    (o.start_s, o.end_s), "needs 0 <= start_s <= end_s")
        for i, fault in enumerate(self.faults):
            path = f"{label}: faults[{i}]"
            if isinstance(fault, CorruptSample):
                fault.validate(path, n_markers)
            elif isinstance(fault, StuckAmplifier):
                fault.validate(path, self.device.n_coils)
            else:
                fault.validate(path)
        require(0.0 <= self.marker_dropout_probability <= 1.0,
                f"{label}: marker_dropout_probability", self.marker_dropout_probability,
                "must be in [0, 1]")
        tracker_hz = self.device.tracker.rate_hz
        for name, tick_s in (("control_rate_hz", 1.0 / self.control_rate_hz),
                             ("plant_config.time_step", self.plant_config.time_step)):
            # The loop and the plant take each tracker sample at their next tick.
            require(tracker_hz * tick_s <= 1 + 1e-9, f"{label}: device.tracker.rate_hz",
                    tracker_hz, f"must be at most one sample a tick: 1 / {name} "
                    f"({1.0 / tick_s:g} Hz)")
        self.estimator.validate(f"{label}: estimator", tracker_hz, 1.0 / self.control_rate_hz)
        if self.duration_s is not None:
            positive(f"{label}: duration_s", self.duration_s)
            require(self.duration_s <= LONGEST_S, f"{label}: duration_s", self.duration_s,
                    f"a run lasts at most {LONGEST_S:g} s")
        for name in ("control_rate_hz", "log_rate_hz"):
            require(getattr(self, name) <= HIGHEST_RATE_HZ, f"{label}: {name}",
                    getattr(self, name), f"must be at most {HIGHEST_RATE_HZ:g} Hz")
        if self.haptics is not None:
            self.haptics.validate(f"{label}: haptics")
            if self.hand is None:
                raise ScenarioError(
                    f"{label}: hand = null: a haptic scenario needs the user's hand "
                    "(hand: !ScriptedHand {...} or !MeshcatHand {...}), whose grip "
                    "engages haptics")
        if self.hand is not None:
            self.hand.validate(f"{label}: hand")
            if isinstance(self.hand, ScriptedHand):
                _check_scripted_hand(self.hand, f"{label}: hand")
        if self.stereo is not None:
            self.stereo.validate(f"{label}: stereo", self.device, f"{label}: device")
            head = self.stereo.head
            check_script_length([(f"{label}: stereo.head.start_s", head.start_s)] + [
                (f"{label}: stereo.head.waypoints[{i}].{name}", getattr(w, name))
                for i, w in enumerate(head.waypoints) for name in ("move_s", "hold_s")])
        self.station.validate(label, self)
        if self.calibration is not None:
            self.calibration.validate(f"{label}: calibration", self.device)
            require(self.hand is None and self.haptics is None, f"{label}: calibration",
                    self.calibration.flight, "a calibration flight flies the instrument "
                    "alone: hand and haptics must be null")


OVERLAY = "--scenario-text"  # what an error in a layer over the file's scenario names


def _check_scripted_hand(hand: "ScriptedHand", path: str) -> None:
    check_script_length([(f"{path}.start_s", hand.start_s)] + [
        (f"{path}.waypoints[{i}].{name}", getattr(w, name))
        for i, w in enumerate(hand.waypoints) for name in ("move_s", "hold_s")])
    for i, event in enumerate(hand.events):
        check_script_length([(f"{path}.events[{i}].at_s", event.at_s)])


def load_scenario(name_or_path: str, name: Optional[str] = None,
                  scenario_text: str = "{}", *more_text: str) -> Scenario:
    """Load one named scenario (default: the file's first) and layer ``scenario_text``
    on it, then each of ``more_text`` in turn."""
    path = resolve_scenario_file(name_or_path)
    source = str(name_or_path)  # as the user named it: a shipped file by its name
    text = read_text_file(path, source)
    raw = parse_mapping(text, source)
    names = [key for key in raw if key != "Defaults"]
    if not names:
        raise ScenarioError(f"{source}: holds no named scenario")
    name = names[0] if name is None else name
    if name not in names:
        raise ScenarioError(f"{source}: no scenario named {name!r}; it has {', '.join(names)}")
    label = f"{path.stem}:{name}"
    if not isinstance(raw[name], (dict, type(None))):
        raise ScenarioError(f"{label}: must be a YAML mapping of the scenario's fields, not "
                            f"{type(raw[name]).__name__} ({raw[name]!r})")
    scenario = load_typed(Scenario, label, raw[name] or {}, lambda: yaml_load_typed(
        schema=Scenario, data=text, child_name=name, defaults=Scenario()),
        lambda cut: yaml_load_typed(schema=Scenario, data=yaml_dump(cut), defaults=Scenario()))
    _resolve_relative_files(scenario, path.absolute().parent, path.parent)
    # (text, its mapping) of each layer that sets something.
    layers = [(text, layered) for text in (scenario_text, *more_text)
              if (layered := parse_mapping(text, OVERLAY))]
    if layers:  # the file's own first: an error after the layers is then theirs
        validate_scenario(_models_resolved(scenario, path.parent), label)
    for text, layered in layers:
        scenario = _layer(scenario, text, layered, label)
        _resolve_relative_files(scenario, Path.cwd(), path.parent)
    scenario = _models_resolved(scenario, path.parent)
    scenario = _with_simulated_device(scenario, [raw[name] or {}, *(m for _, m in layers)],
                                      f"{label} ({OVERLAY})" if layers else label)
    validate_scenario(scenario, f"{label} ({OVERLAY})" if layers else label)
    return scenario


def _with_simulated_device(scenario: Scenario, mappings, label: str) -> Scenario:
    """``scenario`` whose ``station: !SimStation {device: ...}`` is the scenario's
    ``device`` with each layer's station device (``mappings``: the file's scenario,
    then each overlay, as parsed) laid on it in turn."""
    if not isinstance(scenario.station, SimStation) or scenario.station.device is None:
        return scenario
    device = scenario.device
    for mapping in mappings:
        station = mapping.get("station") if isinstance(mapping, dict) else None
        layer = station.get("device") if isinstance(station, dict) else None
        if not isinstance(layer, dict):
            continue
        refused = [key for key in layer if key not in DEVICE_TRUTH_FIELDS]
        if refused:
            raise ScenarioError(
                f"{label}: station.device.{refused[0]}: a simulated station's device may "
                f"differ from the scenario's only in {', '.join(DEVICE_TRUTH_FIELDS)} (the "
                "plant, the coils and the tracker); set the rest in the scenario's device")
        device = layered_device(device, layer, f"{label}: station.device")
    return dataclasses.replace(scenario, station=SimStation(device=device))


def layered_device(device: DeviceConfig, layer: dict, source: str) -> DeviceConfig:
    """``device`` with the parsed YAML mapping ``layer`` laid on it, as Drake layers a
    scenario; a ScenarioError naming ``source`` and the field for what it refuses."""
    return load_typed(DeviceConfig, source, layer,
                      lambda: yaml_load_typed(schema=DeviceConfig, data=yaml_dump(layer),
                                              defaults=device),
                      lambda cut: yaml_load_typed(schema=DeviceConfig, data=yaml_dump(cut),
                                                  defaults=device))


def _models_resolved(scenario: Scenario, here: Path) -> Scenario:
    """``scenario`` with a model scene's ``{here}`` made the scenario file's folder."""
    if scenario.haptics is None or not isinstance(scenario.haptics.scene, ModelScene):
        return scenario
    return dataclasses.replace(scenario, haptics=dataclasses.replace(
        scenario.haptics, scene=resolve_here(scenario.haptics.scene, here)))


def _resolve_relative_files(scenario: Scenario, folder: Path, here: Path) -> None:
    """Make an image heightmap's ``file`` absolute: ``{here}`` is the scenario file's
    folder ``here`` (as in a model scene's URLs); a relative path is against
    ``folder``: the scenario file's for what that file names, the working directory
    for --scenario-text (a path already absolute, from an earlier text, stays)."""
    scene = scenario.haptics.scene if scenario.haptics is not None else None
    heightmap = scene.heightmap if isinstance(scene, DeformableSurface) else None
    if isinstance(heightmap, ImageHeightmap) and heightmap.file:
        file = heightmap.file.replace(HERE, str(here.resolve()))
        heightmap.file = str(folder / Path(file).expanduser())


def _layer(scenario: Scenario, text: str, layered: dict, label: str) -> Scenario:
    """``scenario`` with the YAML mapping ``text`` (parsed: ``layered``) layered on it."""
    return load_typed(Scenario, f"{label} ({OVERLAY})", layered, lambda: yaml_load_typed(
        schema=Scenario, data=text, defaults=scenario),
        lambda cut: yaml_load_typed(schema=Scenario, data=yaml_dump(cut), defaults=scenario))


def scenario_yaml(scenario: Scenario) -> str:
    """``scenario`` as YAML text (``scenario_from_yaml`` reads it back as it was): how
    a study's job carries it to another process (Drake's config types do not pickle)."""
    return yaml_dump_typed(scenario)


def scenario_from_yaml(text: str) -> Scenario:
    return yaml_load_typed(schema=Scenario, data=text)


def with_stereo(scenario: Scenario, label: str) -> Scenario:
    """``scenario`` with the stereo display at its defaults (``maglev run --stereo``)."""
    scenario = dataclasses.replace(scenario, stereo=StereoConfig())
    validate_scenario(scenario, label)
    return scenario


def validate_scenario(s: Scenario, label: str) -> None:
    """Range checks; each error, a ScenarioError, names the field, its value and what
    is allowed."""
    try:
        s.validate(label)
    except ScenarioError:
        raise
    except ValueError as error:
        raise ScenarioError(str(error)) from None
