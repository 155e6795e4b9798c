"""Scenario schema and loading.

A scenario file holds several named scenarios (plus an optional ``Defaults``
entry that is ignored); each is a :class:`Scenario` in YAML, loaded with
``pydrake.common.yaml.yaml_load_typed`` over the defaults, so every field can
be left out; Drake's loader refuses unknown keys, wrong types and unknown
tags, and its error is reported with the field's full path. After loading, the
values are range-checked, each error naming the field, its value and what is
allowed.
"""

import dataclasses
import re
import typing
from dataclasses import dataclass, field
from typing import List, Optional, Union

import yaml
from pydrake.common.yaml import yaml_dump, yaml_dump_typed, yaml_load_data, yaml_load_typed
from pydrake.multibody.plant import MultibodyPlantConfig

from maglev_haptics.diagrams.deformable_scene import DeformableSurface
from maglev_haptics.diagrams.hand_script import MeshcatHand, ScriptedHand
from maglev_haptics.diagrams.lcm_station import LcmStation, SimStation
from maglev_haptics.diagrams.scenario_files import (  # noqa: F401  (the light half, re-exported)
    SCENARIO_DIR, ScenarioError, resolve_scenario_file, scenario_names, shipped_scenario_files,
    yaml_error)
from maglev_haptics.diagrams.scene import HangingBall, PaddleBall, PegInHole
from maglev_haptics.diagrams.stereo_display import StereoConfig
from maglev_haptics.diagrams.waypoints import Waypoint
from maglev_haptics.hardware.config_checks import nonnegative, positive, require, vector
from maglev_haptics.hardware.device import DeviceConfig
from maglev_haptics.systems.device_supervisor import WatchdogConfig
from maglev_haptics.systems.haptic_coupling import CouplingConfig
from maglev_haptics.systems.haptic_supervisor import SupervisorConfig
from maglev_haptics.systems.levitation_controller import ControllerConfig
from maglev_haptics.systems.marker_sensor import Occlusion
from maglev_haptics.systems.fault_injection import (
    CorruptSample, LatencySpike, Shove, StuckAmplifier)
from maglev_haptics.systems.pose_estimator import PoseEstimatorConfig

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


@dataclass
class Haptics:
    """The virtual scene, the coupling that lets the user feel it, and when it is on.

    Haptics is requested from ``enable_at_s`` and engages once the handle is
    gripped; it is requested until ``disable_at_s`` (null: to the end).
    """

    scene: Union[PegInHole, HangingBall, PaddleBall, DeformableSurface] = field(
        default_factory=PegInHole)
    coupling: CouplingConfig = field(default_factory=CouplingConfig)
    supervisor: SupervisorConfig = field(default_factory=SupervisorConfig)
    enable_at_s: float = 2.0  # (s)
    disable_at_s: Optional[float] = None  # (s)

    def validate(self, path: str = "haptics") -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        self.scene.validate(f"{path}.scene")
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
    # The station's plant: the instrument and the glass, point contact (~15 us a step
    # in flight, ~75 us resting on the glass). Unsampled output ports: the plant then
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
    # The device supervisor's watchdogs (systems/device_supervisor.py).
    watchdog: WatchdogConfig = field(default_factory=WatchdogConfig)
    # Faults injected into the simulated station (systems/fault_injection.py).
    faults: List[Union[LatencySpike, CorruptSample, StuckAmplifier, Shove]] = field(
        default_factory=list)

    def validate(self, label: str) -> None:
        """Range checks of every config, each error naming ``label: path.field``, its
        value and what is allowed; then the checks across configs."""
        self.device.validate(f"{label}: device")
        self.controller.validate(f"{label}: controller")
        self.motion.validate(f"{label}: motion")
        self.watchdog.validate(f"{label}: watchdog")
        self.estimator.validate(f"{label}: estimator", self.device.tracker.rate_hz)
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
        positive(f"{label}: control_rate_hz", self.control_rate_hz)
        positive(f"{label}: log_rate_hz", self.log_rate_hz)
        positive(f"{label}: plant_config.time_step", self.plant_config.time_step)
        if self.duration_s is not None:
            positive(f"{label}: duration_s", self.duration_s)
        if self.haptics is not None:
            self.haptics.validate(f"{label}: haptics")
            if self.hand is None:
                raise ScenarioError(
                    f"{label}: hand = null: a haptic scenario needs the user's hand "
                    "(hand: !ScriptedHand {...} or !MeshcatHand {...}), whose grip "
                    "engages haptics")
        if self.hand is not None:
            self.hand.validate(f"{label}: hand")
        if self.stereo is not None:
            self.stereo.validate(f"{label}: stereo", self.device, f"{label}: device")
        self.station.validate(f"{label}: station")
        if isinstance(self.station, LcmStation):
            require(self.stereo is None or self.haptics is not None, f"{label}: stereo", "set",
                    "needs a haptic scene with station: !LcmStation (without one the display "
                    "draws the simulated station's instrument, which a real station has not)")
            require(not isinstance(self.hand, MeshcatHand), f"{label}: hand", "!MeshcatHand",
                    "must be a !ScriptedHand or null with station: !LcmStation (the simulated "
                    "hand is the device's, and device-sim has no Meshcat)")


def _parse_mapping(text: str, source: str) -> dict:
    """The YAML mapping in ``text``, as Drake's loader reads it; a ScenarioError
    naming ``source`` if it is not one."""
    try:
        raw = yaml_load_data(text)
    except yaml.YAMLError as error:
        raise yaml_error(source, error) from None
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise ScenarioError(f"{source}: must be a YAML mapping, not {type(raw).__name__}")
    return raw


def _paths_to(raw, token: str, keys=()):
    """Key paths (tuples) in the parsed YAML ``raw`` whose key, tag or value is ``token``."""
    items = (raw.items() if isinstance(raw, dict)
             else enumerate(raw) if isinstance(raw, list) else ())
    for key, value in items:
        if key == "_tag":
            continue
        tag = value.get("_tag", "").lstrip("!") if isinstance(value, dict) else None
        if key == token or tag == token or (not isinstance(value, (dict, list))
                                            and str(value) == token):
            yield keys + (key,)
        yield from _paths_to(value, token, keys + (key,))


def _field_path(keys) -> str:
    return "".join(f"[{key}]" if isinstance(key, int) else f".{key}" for key in keys).lstrip(".")


def _schema_at(raw, keys):
    """The config class that the YAML at ``keys`` fills (a Union's member by its tag),
    or None where the path leaves the dataclasses."""
    schema, node = Scenario, raw
    for key in keys:
        node = node[key]
        if isinstance(key, int):
            schema = typing.get_args(schema)[0]
        elif dataclasses.is_dataclass(schema):
            schema = typing.get_type_hints(schema).get(key)
        else:
            return None
        options = [a for a in typing.get_args(schema) if a is not type(None)]
        if typing.get_origin(schema) is Union:
            tag = node.get("_tag", "").lstrip("!") if isinstance(node, dict) else ""
            named = {option.__name__: option for option in options}
            schema = options[0] if len(options) == 1 else named.get(tag, options[0])
    return schema


def _check_union_tags(raw, schema, keys=()) -> None:
    """Refuse an untagged mapping where a field holds one of several kinds: Drake's
    loader would silently read it as the Union's first kind (a hanging ball's
    ``scene: {contact: ...}`` as a fresh PegInHole), and keep a scalar there as the
    field's value. The checks Drake lacks."""
    if typing.get_origin(schema) is Union:
        options = [a for a in typing.get_args(schema) if a is not type(None)]
        kinds = [option for option in options if dataclasses.is_dataclass(option)]
        if len(kinds) > 1 and raw is not None and not isinstance(raw, dict):
            # Drake's loader would keep the scalar as the field's value.
            raise ScenarioError(f"{_field_path(keys)} = {_flow_yaml(raw)}: must be one of "
                                + ", ".join(f"!{kind.__name__} {{...}}" for kind in kinds)
                                + (", or null" if type(None) in typing.get_args(schema) else ""))
        if len(options) > 1 and isinstance(raw, dict):
            named = {option.__name__: option for option in options}
            tags = ", ".join(f"!{name}" for name in named)
            tag = raw.get("_tag", "").lstrip("!")
            if not tag:
                raise ScenarioError(f"{_field_path(keys)}: needs a tag to choose its kind, one "
                                    f"of {tags} (e.g. {keys[-1]}: !{options[0].__name__} {{}})")
            _check_union_tags(raw, named.get(tag), keys)
        elif len(options) == 1:
            _check_union_tags(raw, options[0], keys)
    elif typing.get_origin(schema) is list and isinstance(raw, list):
        for i, item in enumerate(raw):
            _check_union_tags(item, typing.get_args(schema)[0], keys + (i,))
    elif dataclasses.is_dataclass(schema) and isinstance(raw, dict):
        hints = typing.get_type_hints(schema)
        for key, value in raw.items():
            if key in hints:
                _check_union_tags(value, hints[key], keys + (key,))


# What Drake's YAML loader raises on data that does not fit the schema (its Python
# half asserts, converts with float() and iterates).
LOAD_ERRORS = (RuntimeError, ValueError, TypeError, AssertionError)


def _with_only(raw: dict, keys) -> dict:
    """``raw`` cut down to the field at ``keys`` (its whole value) and the tags of
    the mappings on the way."""
    if not keys:
        return raw
    cut = {"_tag": raw["_tag"]} if "_tag" in raw else {}
    cut[keys[0]] = _with_only(raw[keys[0]], keys[1:]) if len(keys) > 1 else raw[keys[0]]
    return cut


def _failing_field(raw: dict, load_raw) -> tuple:
    """The deepest key path in ``raw`` whose field alone ``load_raw`` still refuses
    (down through mappings; a list is one field); () if none does alone."""
    keys, node = (), raw
    while isinstance(node, dict):
        for key, value in node.items():
            if key == "_tag":
                continue
            try:
                load_raw(_with_only(raw, keys + (key,)))
            except LOAD_ERRORS:
                keys, node = keys + (key,), value
                break
        else:
            break
    return keys


def _load_typed(source: str, raw: dict, load, load_raw):
    """``load()`` (Drake's yaml_load_typed, which checks keys, types and tags); its
    error as a ScenarioError that names the field's path: found in ``raw`` from the
    names the error quotes, else by loading ``raw``'s fields alone (``load_raw(raw)``)."""
    try:
        _check_union_tags(raw, Scenario)
        return load()
    except ScenarioError as error:
        raise ScenarioError(f"{source}: {error}") from None
    except LOAD_ERRORS as error:
        # Its one assert on data: a value where a mapping of fields belongs.
        message = ("expected a mapping of its fields" if isinstance(error, AssertionError)
                   else (str(error).splitlines() or [type(error).__name__])[0])
        # Drake names a Union's options as classes: say them as the tags to write.
        message = re.sub(r"\(\((.*)\)\)", lambda options: "(" + ", ".join(
            f"!{name}" for name in re.findall(r"<class '[\w.]*?(\w+)'>", options[1])
            if name != "NoneType") + ")", message)
        tokens = re.findall(r"'([^']+)'", message)
        paths = sorted({path for token in tokens for path in _paths_to(raw, token)})
        if paths and "unknown to the schema" in message:
            parent = _schema_at(raw, paths[0][:-1])
            if dataclasses.is_dataclass(parent):
                message = (f"unknown field; {parent.__name__} has "
                           + ", ".join(f.name for f in dataclasses.fields(parent)))
        if not paths:  # the error names no field: find it, and say what it takes
            keys = _failing_field(raw, load_raw)
            if keys:
                value = raw
                for key in keys:
                    value = value[key]
                raise ScenarioError(
                    f"{source}: {_field_path(keys)} = {_flow_yaml(value)}: must be "
                    f"{_type_name(_schema_at(raw, keys))} ({message})") from None
        where = ", ".join(_field_path(path) for path in paths)
        raise ScenarioError(f"{source}: {where + ': ' if where else ''}{message}") from None


def _flow_yaml(value) -> str:
    return yaml.safe_dump(value, default_flow_style=True, width=1000).strip().removesuffix(
        "...").strip()


def _type_name(hint) -> str:
    """``float``, ``List[float]``, ``Optional[float]``: a schema type as a user reads it."""
    return hint.__name__ if isinstance(hint, type) else str(hint).replace("typing.", "")


def load_scenario(name_or_path: str, name: Optional[str] = None,
                  scenario_text: str = "{}", *more_text: str) -> Scenario:
    """Load one named scenario (default: the file's first) and layer ``scenario_text``
    on it, then each of ``more_text`` in turn."""
    path = resolve_scenario_file(name_or_path)
    text = path.read_text()
    raw = _parse_mapping(text, str(path))
    names = [key for key in raw if key != "Defaults"]
    if not names:
        raise ScenarioError(f"{path}: holds no named scenario")
    name = names[0] if name is None else name
    if name not in names:
        raise ScenarioError(f"{path}: no scenario named {name!r}; it has {', '.join(names)}")
    label = f"{path.stem}:{name}"
    scenario = _load_typed(label, raw[name] or {}, lambda: yaml_load_typed(
        schema=Scenario, data=text, child_name=name, defaults=Scenario()),
        lambda cut: yaml_load_typed(schema=Scenario, data=yaml_dump(cut), defaults=Scenario()))
    for layer in (scenario_text, *more_text):
        scenario = _layer(scenario, layer, label)
    validate_scenario(scenario, label)
    return scenario


def _layer(scenario: Scenario, text: str, label: str) -> Scenario:
    """``scenario`` with the YAML mapping ``text`` layered on it."""
    layered = _parse_mapping(text, "--scenario-text")
    return _load_typed(f"{label} (--scenario-text)", layered, lambda: yaml_load_typed(
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
