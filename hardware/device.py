"""The device description: coil array, instruments, amplifiers, display, trackers.

Every number defaults to the reference device of docs/device_model.md (the
paper's device plus the stated physical assumptions) and every field is settable
from a scenario's ``device:`` block. SI units throughout; frames as in docs/architecture.md (W display, A coil
array, C_j coil j, I instrument).
"""

import copyreg
import dataclasses
import math
from dataclasses import dataclass, field
from typing import List, Optional

import numpy as np
from pydrake.common.schema import Transform
from pydrake.common.yaml import yaml_dump_typed, yaml_load_typed
from pydrake.math import RigidTransform

from maglev_haptics.hardware.config_checks import nonnegative, positive, require

NDFEB_DENSITY_KG_M3 = 7500.0
# A magnet's strength or a coil's wrench per ampere against the model: a device outside
# this is another device, not a calibration of this one.
MODEL_SCALE_RANGE = (0.5, 1.5)
MAX_COM_OFFSET_M = 0.02  # a centre of mass past this is off the instrument's body (m)


def _transform_from_yaml(text: str) -> Transform:
    return yaml_load_typed(schema=Transform, data=text)


# Drake's schema Transform does not pickle; a device config does (sweeps and worker
# processes carry scenarios): through its YAML.
copyreg.pickle(Transform, lambda value: (_transform_from_yaml, (yaml_dump_typed(value),)))
INSTRUMENT_KINDS = ("two_magnet", "four_magnet")


@dataclass
class CoilSpec:
    """One cylindrical air-core coil (all coils of the array are alike)."""

    inner_diameter_m: float = 0.010  # assumption (docs/device_model.md)
    outer_diameter_m: float = 0.025  # paper
    height_m: float = 0.030  # paper
    turns: int = 1000  # paper
    resistance_ohm: float = 6.5  # assumption
    inductance_h: float = 6.0e-3  # assumption


@dataclass
class CoilArraySpec:
    """Hexagonal close-packed planar array; coil tops in the plane z_A = 0.

    Rows run along x at y = (k - (n_rows - 1) / 2) * row_spacing_m; the row with
    the lowest y has ``row_counts[0]`` coils; within a row coils sit at x centred
    on 0 with ``pitch_m`` spacing. Coils are numbered row by row from the lowest
    y, x ascending within a row.
    """

    pitch_m: float = 0.026  # centre distance along a row
    row_spacing_m: float = 0.022517  # pitch * sqrt(3) / 2
    row_counts: List[int] = field(default_factory=lambda: [5, 6, 5, 6, 5])

    def coil_positions_A(self) -> np.ndarray:
        """Coil top-face centres p_ACj, shape (n_coils, 3) [m]."""
        positions = []
        n_rows = len(self.row_counts)
        for row, count in enumerate(self.row_counts):
            y = (row - (n_rows - 1) / 2) * self.row_spacing_m
            for k in range(count):
                x = (k - (count - 1) / 2) * self.pitch_m
                positions.append((x, y, 0.0))
        return np.array(positions, dtype=float)

    @property
    def n_coils(self) -> int:
        return int(sum(self.row_counts))


@dataclass
class MagnetSpec:
    """An axially magnetized cylindrical magnet (NdFeB N42 by default)."""

    diameter_m: float = 0.0254
    height_m: float = 0.0127
    remanence_t: float = 1.30  # Br; magnetization M = Br / mu0 along the axis
    density_kg_m3: float = NDFEB_DENSITY_KG_M3

    @property
    def volume_m3(self) -> float:
        return math.pi * (self.diameter_m / 2) ** 2 * self.height_m

    @property
    def mass_kg(self) -> float:
        return self.volume_m3 * self.density_kg_m3


@dataclass
class InstrumentSpec:
    """A levitated instrument: a rigid body carrying magnets and tracker markers.

    Positions are in the instrument frame I (origin at the centroid of the
    magnet centres, z along the common magnetization axis, x along the magnet
    row). The body without its magnets is modelled as a uniform box centred on
    I (``body_size_m``) so that mass and inertia are consistent.
    """

    kind: str
    mass_kg: float  # total, magnets included
    magnet: MagnetSpec
    p_IM_m: List[List[float]]  # magnet centres in I [m]
    p_IK_m: List[List[float]]  # tracker marker positions in I [m]
    body_size_m: List[float]  # box (x, y, z) extents of the non-magnet body [m]
    model_url: str

    @property
    def p_IM(self) -> np.ndarray:
        return np.asarray(self.p_IM_m, dtype=float)

    @property
    def p_IK(self) -> np.ndarray:
        return np.asarray(self.p_IK_m, dtype=float)

    @property
    def rest_height_m(self) -> float:
        """Height of I above the display top when resting level on it [m]."""
        return self.body_size_m[2] / 2

    def inertia_about_I(self) -> np.ndarray:
        """Rotational inertia about I's origin in I, (3, 3) [kg m^2]."""
        magnet = self.magnet
        r, h, m = magnet.diameter_m / 2, magnet.height_m, magnet.mass_kg
        own = np.diag([m * (3 * r**2 + h**2) / 12] * 2 + [m * r**2 / 2])
        inertia = np.zeros((3, 3))
        for p in self.p_IM:
            inertia += own + m * (p @ p * np.eye(3) - np.outer(p, p))
        body_mass = self.mass_kg - len(self.p_IM) * m
        a, b, c = self.body_size_m
        inertia += body_mass / 12 * np.diag([b**2 + c**2, a**2 + c**2, a**2 + b**2])
        return inertia


def _marker_triangle(radius_m: float, height_m: float) -> List[List[float]]:
    """Three markers on an equilateral triangle above the instrument [m]."""
    return [
        [radius_m * math.cos(a), radius_m * math.sin(a), height_m]
        for a in (math.pi / 2, math.pi / 2 + 2 * math.pi / 3, math.pi / 2 + 4 * math.pi / 3)
    ]


def default_instrument(kind: str) -> InstrumentSpec:
    """The paper's instruments with the magnets of docs/device_model.md."""
    if kind == "two_magnet":
        return InstrumentSpec(
            kind=kind,
            mass_kg=0.125,
            magnet=MagnetSpec(diameter_m=0.0254, height_m=0.0127),
            p_IM_m=[[-0.020, 0.0, 0.0], [0.020, 0.0, 0.0]],
            p_IK_m=_marker_triangle(0.035, 0.060),
            body_size_m=[0.070, 0.030, 0.014],
            model_url="package://maglev_haptics/two_magnet_instrument.sdf",
        )
    if kind == "four_magnet":
        return InstrumentSpec(
            kind=kind,
            mass_kg=0.075,
            magnet=MagnetSpec(diameter_m=0.015875, height_m=0.009525),
            p_IM_m=[[-0.020, -0.020, 0.0], [0.020, -0.020, 0.0],
                    [-0.020, 0.020, 0.0], [0.020, 0.020, 0.0]],
            p_IK_m=_marker_triangle(0.035, 0.060),
            body_size_m=[0.058, 0.058, 0.011],
            model_url="package://maglev_haptics/four_magnet_instrument.sdf",
        )
    raise ValueError(
        f"device.instrument = {kind!r}: must be one of {', '.join(INSTRUMENT_KINDS)}")


@dataclass
class AmplifierSpec:
    """Current-mode coil amplifiers (one per coil)."""

    current_limit_a: float = 4.0  # peak per coil; allocator and amplifier both respect it
    bandwidth_hz: float = 1000.0  # closed-loop current bandwidth, first-order lag


@dataclass
class DisplaySpec:
    """The flat display lying on the coil array; its top surface is W's z = 0."""

    thickness_m: float = 0.010  # paper: "under 10 mm" with the backlight
    size_m: List[float] = field(default_factory=lambda: [0.4738, 0.2961])  # 22" 16:10 active area
    resolution_px: List[int] = field(default_factory=lambda: [1680, 1050])  # width, height
    refresh_hz: float = 120.0  # frames a second, alternating eyes behind the shutter glasses
    # Pose of the active area's centre D in W, [x, y, z, roll, pitch, yaw] (m, rad): zero
    # by W's definition; set it to model a display that sits off its calibrated place.
    # Its x runs along the long edge (the image's rows), its y to the image's top edge.
    pose_W: List[float] = field(default_factory=lambda: [0.0] * 6)


def _glasses_markers() -> List[List[float]]:
    """Four reflective markers on the left temple of the glasses, in G (m): a flat,
    asymmetric star as on a Polaris passive tool, facing the tracker at the user's left."""
    return [[-0.078, -0.010, 0.010], [-0.078, 0.015, 0.045],
            [-0.078, -0.020, 0.070], [-0.078, 0.010, 0.095]]


@dataclass
class GlassesSpec:
    """The shutter glasses: frame G has its origin midway between the eyes, x towards
    the right eye, y down the face, z along the line of sight (a camera's axes)."""

    ipd_m: float = 0.063  # interpupillary distance, the adult mean (m)
    p_GK_m: List[List[float]] = field(default_factory=_glasses_markers)  # tracker markers (m)


@dataclass
class HeadTrackerSpec:
    """Optical tracker of the glasses (NDI Polaris Vicra by default)."""

    rate_hz: float = 10.0  # the paper's head tracker: ~10 Hz
    noise_m: float = 1.0e-4  # standard deviation per marker coordinate (paper: ~0.1 mm)
    # Capture to availability (s). Assumed: the paper gives none, only a "noticeable
    # lag"; a Polaris over a serial link reports tens of ms.
    latency_s: float = 0.030


@dataclass
class TrackerSpec:
    """Optical tracker of the instrument's markers (Optotrak Certus by default)."""

    rate_hz: float = 860.0
    noise_m: float = 1.0e-5  # standard deviation per marker coordinate
    latency_s: float = 1.5e-3  # measurement to availability (Optotrak ~1-2 ms)
    # The pose of the frame T the tracker reports markers in, in W: where the tracker
    # is bolted against the display. Nominal T is W; ``maglev calibrate fit`` measures it.
    X_WT: Transform = field(default_factory=Transform)

    def pose_WT(self) -> RigidTransform:
        """X_WT as a RigidTransform."""
        return self.X_WT.GetDeterministicValue()


@dataclass
class ThermalSpec:
    """Thermal behaviour of one coil of the array (all coils alike, each its own
    first-order RC to ambient; see ``thermal.py``). Assumptions, not from the paper.
    """

    ambient_temperature_c: float = 25.0  # air under the display [deg C]
    # Class-B (130 C) insulation less a margin for the hot spot inside the winding [deg C].
    max_winding_temperature_c: float = 100.0
    # Effective coil-to-ambient resistance [K/W]: epoxy-potted coils on an
    # aluminium base plate with a fan blowing through the array; the gaps of
    # the close packing expose little side surface, so this is the
    # plausible-but-good end (~50 W/(m^2 K) over ~4e-3 m^2 in parallel with
    # ~5 K/W of conduction into the plate). With it the continuous current
    # limit is ~1.9 A, and sustained extra force reaches ~4 N only near the
    # display, the paper's "about 4 N, limited by coil heating".
    thermal_resistance_k_per_w: float = 2.5
    # Copper share of the winding cross-section; 0.65 is what 1000 turns at
    # 6.5 ohm imply for the 25/10/30 mm winding (0.43 mm wire).
    copper_fill_factor: float = 0.65
    heat_capacity_j_per_k: Optional[float] = None  # None: copper mass x its specific heat [J/K]
    # Each coil's own (n_coils each, as a calibration measures them); None: the scalar
    # fields above for every coil [K/W], [J/K].
    thermal_resistances_k_per_w: Optional[List[float]] = None
    heat_capacities_j_per_k: Optional[List[float]] = None
    resistance_reference_temperature_c: float = 20.0  # where CoilSpec.resistance_ohm holds [deg C]
    resistance_temperature_coefficient_per_k: float = 0.00393  # copper [1/K]


@dataclass
class DeviceConfig:
    """The whole device. ``DeviceConfig(instrument="four_magnet")`` picks the 4-magnet one.

    ``instrument`` selects a kind; ``magnet`` and ``instrument_mass_kg``, when
    set, override that kind's defaults (the shipped body model must then match,
    which ``instrument_spec()`` users check).
    """

    instrument: str = "two_magnet"
    magnet: Optional[MagnetSpec] = None  # None: the kind's magnets
    instrument_mass_kg: Optional[float] = None  # None: the kind's mass
    # The centre of mass in I (m): nominal at I's origin; a tool or a handle off-centre
    # moves it, and the gravity torque about I with it.
    instrument_com_offset_m: List[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    # Each magnet's strength (one per magnet of the instrument, in p_IM's order) and each
    # coil's wrench per ampere (n_coils), as scales on the electromagnetic model; None is
    # 1.0 for each: a grade's +-3 % of remanence, a coil's windings and placement.
    magnet_strength_scales: Optional[List[float]] = None
    coil_force_scales: Optional[List[float]] = None
    coil: CoilSpec = field(default_factory=CoilSpec)
    array: CoilArraySpec = field(default_factory=CoilArraySpec)
    amplifier: AmplifierSpec = field(default_factory=AmplifierSpec)
    display: DisplaySpec = field(default_factory=DisplaySpec)
    tracker: TrackerSpec = field(default_factory=TrackerSpec)
    glasses: GlassesSpec = field(default_factory=GlassesSpec)
    head_tracker: HeadTrackerSpec = field(default_factory=HeadTrackerSpec)
    thermal: ThermalSpec = field(default_factory=ThermalSpec)

    def validate(self, path: str = "device") -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        require(self.instrument in INSTRUMENT_KINDS, f"{path}.instrument", self.instrument,
                f"must be one of {', '.join(INSTRUMENT_KINDS)}")
        if self.instrument_mass_kg is not None:
            positive(f"{path}.instrument_mass_kg", self.instrument_mass_kg)
        if self.magnet is not None:
            for name in ("diameter_m", "height_m", "remanence_t", "density_kg_m3"):
                positive(f"{path}.magnet.{name}", getattr(self.magnet, name))
        coil, array = self.coil, self.array
        for name in ("outer_diameter_m", "height_m", "resistance_ohm", "inductance_h"):
            positive(f"{path}.coil.{name}", getattr(coil, name))
        nonnegative(f"{path}.coil.inner_diameter_m", coil.inner_diameter_m)
        require(coil.inner_diameter_m < coil.outer_diameter_m, f"{path}.coil.inner_diameter_m",
                coil.inner_diameter_m, f"must be < outer_diameter_m ({coil.outer_diameter_m})")
        require(isinstance(coil.turns, int) and coil.turns > 0, f"{path}.coil.turns",
                coil.turns, "must be a positive integer")
        positive(f"{path}.array.pitch_m", array.pitch_m)
        positive(f"{path}.array.row_spacing_m", array.row_spacing_m)
        require(len(array.row_counts) > 0 and all(c > 0 for c in array.row_counts),
                f"{path}.array.row_counts", array.row_counts,
                "must be a non-empty list of positive counts")
        require(array.pitch_m >= coil.outer_diameter_m, f"{path}.array.pitch_m", array.pitch_m,
                f"must be >= the coil's outer diameter ({coil.outer_diameter_m} m): coils "
                "cannot overlap")
        positive(f"{path}.amplifier.current_limit_a", self.amplifier.current_limit_a)
        positive(f"{path}.amplifier.bandwidth_hz", self.amplifier.bandwidth_hz)
        positive(f"{path}.display.thickness_m", self.display.thickness_m)
        positive(f"{path}.tracker.rate_hz", self.tracker.rate_hz)
        nonnegative(f"{path}.tracker.noise_m", self.tracker.noise_m)
        nonnegative(f"{path}.tracker.latency_s", self.tracker.latency_s)
        require(self.tracker.X_WT.IsDeterministic() and self.tracker.X_WT.base_frame is None,
                f"{path}.tracker.X_WT", self.tracker.X_WT,
                "must be a fixed pose in W (no random distribution, no base_frame)")
        offset = np.asarray(self.instrument_com_offset_m, dtype=float)
        require(offset.shape == (3,) and np.all(np.isfinite(offset))
                and np.linalg.norm(offset) <= MAX_COM_OFFSET_M, f"{path}.instrument_com_offset_m",
                self.instrument_com_offset_m,
                f"must be [x, y, z] in I (m), at most {MAX_COM_OFFSET_M} m from I's origin")
        for name in ("thermal_resistances_k_per_w", "heat_capacities_j_per_k"):
            values = getattr(self.thermal, name)
            if values is not None:
                array_values = np.asarray(values, dtype=float)
                require(array_values.shape == (array.n_coils,) and np.all(array_values > 0)
                        and np.all(np.isfinite(array_values)), f"{path}.thermal.{name}", values,
                        f"must be {array.n_coils} positive numbers (one per coil), or null for "
                        "the scalar field")
        n_magnets = len(default_instrument(self.instrument).p_IM_m)
        for name, count in (("magnet_strength_scales", n_magnets),
                            ("coil_force_scales", array.n_coils)):
            scales = getattr(self, name)
            if scales is not None:
                values = np.asarray(scales, dtype=float)
                require(values.shape == (count,) and np.all(values >= MODEL_SCALE_RANGE[0])
                        and np.all(values <= MODEL_SCALE_RANGE[1]), f"{path}.{name}", scales,
                        f"must be {count} numbers (one per {name.split('_')[0]}) in "
                        f"[{MODEL_SCALE_RANGE[0]}, {MODEL_SCALE_RANGE[1]}], or null for 1.0 each")

    def with_payload(self, payload_kg: float, p_IP_m) -> "DeviceConfig":
        """This device carrying a point mass ``payload_kg`` (kg) at p_IP_m (m, in I): its
        mass and centre of mass combined."""
        if payload_kg == 0.0:
            return self
        mass_kg = self.instrument_spec().mass_kg
        total_kg = mass_kg + payload_kg
        com = (mass_kg * np.asarray(self.instrument_com_offset_m, dtype=float)
               + payload_kg * np.asarray(p_IP_m, dtype=float)) / total_kg
        return dataclasses.replace(self, instrument_mass_kg=total_kg,
                                   instrument_com_offset_m=[float(v) for v in com])

    def model_scales(self) -> tuple:
        """(magnet scales (n_magnets,), coil scales (n_coils,)): the wrench model's
        per-magnet and per-coil factors, ones where the config leaves them null."""
        n_magnets = len(self.instrument_spec().p_IM_m)
        magnets = np.ones(n_magnets) if self.magnet_strength_scales is None \
            else np.asarray(self.magnet_strength_scales, dtype=float)
        coils = np.ones(self.n_coils) if self.coil_force_scales is None \
            else np.asarray(self.coil_force_scales, dtype=float)
        return np.ascontiguousarray(magnets), np.ascontiguousarray(coils)

    def instrument_spec(self) -> InstrumentSpec:
        spec = default_instrument(self.instrument)
        if self.magnet is not None:
            spec = dataclasses.replace(spec, magnet=self.magnet)
        if self.instrument_mass_kg is not None:
            spec = dataclasses.replace(spec, mass_kg=self.instrument_mass_kg)
        return spec

    @property
    def n_coils(self) -> int:
        return self.array.n_coils

    @property
    def p_WA(self) -> np.ndarray:
        """Coil-array origin in W: the coil tops lie one display thickness below [m]."""
        return np.array([0.0, 0.0, -self.display.thickness_m])
