"""Workspace study: what the coils can do over the instrument's motion range.

For each instrument and each pose of a grid over x, y, height, tilt and yaw:

- the condition number of the 6 x 27 wrench matrix A (``magnetics``), with
  its torque rows divided by the instrument's lever length L (the RMS distance
  of the magnet centres from I: 20 mm for the 2-magnet, 28.3 mm for the 4-magnet
  instrument) so that they read as the force pair at the magnets that makes the
  same torque, in N/A like the force rows;
- the hover current of the busiest coil [A] and the hover power [W] (sum of
  I_j^2 R at the coils' 20 C resistance) of the minimum-norm allocation
  I = A^+ w_weight, the allocator's solution whenever no coil saturates;
- the smallest possible busiest-coil current that carries the weight [A]
  (``hardware.limits.hover_current_a``, a linear program), which decides
  whether the instrument can hover there within a current limit;
- the largest extra force along +-x, +-y, +-z [N] and torque about +-x, +-y,
  +-z [N m] (W axes, about I's origin) on top of the weight, within the
  amplifiers' peak current and within the coils' continuous thermal limit
  (``hardware.limits.max_added_wrench``).

Every quantity but ``base_clearance_m`` is NaN where the instrument's base would
be inside the display glass or the weight is out of the coils' reach (the
magnets beyond the wrench table, or A losing rank); everything but that and
``hover_current_minmax_a`` is NaN where no allocation within the peak limit
carries the weight, and the thermal-limit force and torque are NaN where none
within the continuous limit does. ``workspace_study`` returns plain lists and
dicts with every NaN or infinity written as ``None``, so ``json.dumps`` (even
with ``allow_nan=False``) writes standard JSON; ``plot_workspace`` reads them
back as NaN.

The slices (each pose three small linear programs, ~8 ms):

- ``xy``: level, yaw 0, an x-y grid at a few heights of I above W's z = 0;
- ``height``: level over the array centre, a range of heights;
- ``tilt``: over the centre, tilted about W's x (roll) or y (pitch), times heights;
- ``yaw``: level over the centre, yawed 0..90 deg, times heights. The array
  is mirror-symmetric in x and in y and both instruments are symmetric under
  a half turn, so over the centre 0..90 deg covers every yaw (and 0..35 deg
  every tilt of up to 35 deg about x or y).

Measured on a 2-core machine with the wrench tables cached: the
default study (2 instruments x 3,190 poses) takes 55 s and its plots 14 s;
``WorkspaceSettings.quick()`` (2 x 90 poses) 2 s and its plots ~10 s.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import LogNorm  # noqa: E402
from matplotlib.patches import Circle, Rectangle  # noqa: E402
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter  # noqa: E402
from pydrake.math import RollPitchYaw, RotationMatrix  # noqa: E402

from maglev_haptics.analysis.parallel import map_jobs  # noqa: E402
from maglev_haptics.analysis.run_plots import save_figure  # noqa: E402
from maglev_haptics.diagrams.motion import MAX_TILT_DEG, base_clearance_m  # noqa: E402
from maglev_haptics.hardware.device import INSTRUMENT_KINDS, DeviceConfig  # noqa: E402
from maglev_haptics.hardware.limits import (  # noqa: E402
    AXIS_DIRECTIONS, LIMIT_KINDS, coil_current_limit_a, hover_current_a, hover_workspace_A,
    max_added_wrench, weight_wrench)
from maglev_haptics.hardware.magnetics import MagneticsModel, load_magnetics  # noqa: E402
from maglev_haptics.hardware.thermal import coil_thermal, winding_resistance_ohm  # noqa: E402
from maglev_haptics.systems.current_allocator import minimum_norm_currents  # noqa: E402

# Labels of the six axis directions, in hardware.limits.AXIS_DIRECTIONS' order.
DIRECTIONS = ("+x", "+y", "+z", "-x", "-y", "-z")
POWER_TEMPERATURE_C = 20.0  # the winding temperature the hover power is quoted at [deg C]
# The paper's horizontal motion range, a square centred on W's origin [m].
PAPER_RANGE_M = 0.100
# Below this smallest-to-largest singular value ratio A has lost rank: the
# magnets are out of the coils' reach.
_RANK_TOLERANCE = 1e-9
_WRENCH_DIRECTIONS = np.zeros((12, 6))
_WRENCH_DIRECTIONS[:6, :3] = AXIS_DIRECTIONS
_WRENCH_DIRECTIONS[6:, 3:] = AXIS_DIRECTIONS


@dataclass
class WorkspaceSettings:
    """The grids of the study. Heights are of I's origin above W's z = 0 [m]."""

    instruments: tuple[str, ...] = INSTRUMENT_KINDS
    x_range_m: tuple[float, float] = (-0.06, 0.06)  # x of I in W for the x-y maps [m]
    y_range_m: tuple[float, float] = (-0.06, 0.06)  # y of I in W for the x-y maps [m]
    xy_steps: int = 25  # grid points along x and along y (5 mm apart by default)
    map_heights_m: tuple[float, ...] = (0.010, 0.020, 0.030, 0.040)  # heights of the x-y maps [m]
    height_range_m: tuple[float, float] = (0.005, 0.060)  # heights of the profiles [m]
    height_steps: int = 23  # (2.5 mm apart by default)
    tilt_range_deg: tuple[float, float] = (0.0, 35.0)  # about W's x and about its y [deg]
    tilt_steps: int = 8
    yaw_range_deg: tuple[float, float] = (0.0, 90.0)  # [deg]
    yaw_steps: int = 13

    @classmethod
    def quick(cls) -> WorkspaceSettings:
        """Coarse grids for tests (~2 s for both instruments)."""
        return cls(xy_steps=5, map_heights_m=(0.015, 0.030), height_steps=4, tilt_steps=3,
                   yaw_steps=3)

    def check(self) -> None:
        """ValueError naming the first bad field."""
        for kind in self.instruments:
            if kind not in INSTRUMENT_KINDS:
                raise ValueError(f"instruments: {kind!r} must be one of "
                                 f"{', '.join(INSTRUMENT_KINDS)}")
        for name in ("xy_steps", "height_steps", "tilt_steps", "yaw_steps"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} = {getattr(self, name)!r}: must be at least 1")
        if not self.map_heights_m:
            raise ValueError("map_heights_m: must name at least one height [m]")
        if max(abs(t) for t in self.tilt_range_deg) > MAX_TILT_DEG:
            raise ValueError(f"tilt_range_deg = {self.tilt_range_deg!r}: beyond the "
                             f"{MAX_TILT_DEG:.0f} deg the electromagnetic model is validated for")


def lever_length_m(config: DeviceConfig) -> float:
    """L [m]: RMS distance of the magnet centres from I, the torque rows' scale."""
    p_IM = config.instrument_spec().p_IM
    return float(np.sqrt(np.mean(np.sum(p_IM**2, axis=1))))


def scaled_condition_number(A: np.ndarray, lever_m: float) -> float:
    """cond(diag(1, 1, 1, 1/L, 1/L, 1/L) A) for the (6, n) wrench matrix A and
    lever length L [m]; inf where A has lost rank."""
    singular = np.linalg.svd(np.vstack([A[:3], A[3:] / lever_m]), compute_uv=False)
    if singular[-1] <= _RANK_TOLERANCE * singular[0]:
        return math.inf
    return float(singular[0] / singular[-1])


def _nan_metrics(clearance_m: float) -> dict:
    """pose_metrics' dict with every entry NaN but the base clearance [m]."""
    nan_directions = {label: math.nan for label in DIRECTIONS}
    return {
        "base_clearance_m": clearance_m,
        "condition_number": math.nan,
        "hover_current_a": math.nan,
        "hover_current_minmax_a": math.nan,
        "hover_power_w": math.nan,
        "max_force_n": {limit: dict(nan_directions) for limit in LIMIT_KINDS},
        "max_torque_nm": {limit: dict(nan_directions) for limit in LIMIT_KINDS},
    }


def pose_metrics(magnetics: MagneticsModel, config: DeviceConfig, p_WI, R_WI) -> dict:
    """The study's numbers for the instrument of ``config`` at p_WI (3,) [m], R_WI (3, 3).

    Keys (NaN as the module docstring says): base_clearance_m [m] (lowest corner
    of the instrument's base above the glass), condition_number (torque rows
    scaled by ``lever_length_m``), hover_current_a [A] and hover_power_w [W]
    (minimum-norm allocation), hover_current_minmax_a [A] (smallest possible
    busiest coil), and max_force_n [N] / max_torque_nm [N m], each
    {limit: {direction: value}} for limit in LIMIT_KINDS and direction in DIRECTIONS.
    """
    p_WI = np.asarray(p_WI, dtype=float)
    R_WI = np.asarray(R_WI, dtype=float)
    spec = config.instrument_spec()
    clearance = base_clearance_m(np.r_[p_WI, RollPitchYaw(RotationMatrix(R_WI)).vector()], spec)
    metrics = _nan_metrics(clearance)
    if clearance < 0:
        return metrics
    # A's axes are W's (docs/architecture.md, frames), so R_AI = R_WI.
    A = magnetics.wrench_matrix_from(p_WI - config.p_WA, R_WI)
    condition = scaled_condition_number(A, lever_length_m(config))
    if not math.isfinite(condition):
        return metrics
    weight = weight_wrench(config)
    minmax = hover_current_a(A, weight)
    if not math.isfinite(minmax):
        return metrics
    metrics["hover_current_minmax_a"] = minmax
    if minmax > coil_current_limit_a(config, "peak"):
        return metrics
    currents = minimum_norm_currents(A, weight)
    resistance = float(winding_resistance_ohm(coil_thermal(config), POWER_TEMPERATURE_C))
    metrics.update(condition_number=condition,
                   hover_current_a=float(np.max(np.abs(currents))),
                   hover_power_w=float(np.sum(currents**2) * resistance))
    for limit in LIMIT_KINDS:
        current_limit = coil_current_limit_a(config, limit)
        if minmax > current_limit:
            continue
        try:
            added, _ = max_added_wrench(A, weight, _WRENCH_DIRECTIONS, current_limit)
        except ValueError:  # at the limit to within the LP's tolerance: treat as out of reach
            continue
        metrics["max_force_n"][limit] = dict(zip(DIRECTIONS, added[:6].tolist()))
        metrics["max_torque_nm"][limit] = dict(zip(DIRECTIONS, added[6:].tolist()))
    return metrics


def _slices(settings: WorkspaceSettings) -> dict:
    """name -> (coordinates, poses): the maps' axes in order (name -> values, in
    m or deg) and the poses (p_WI, R_WI) of the grid in C order."""
    def line(span, steps):
        return np.linspace(span[0], span[1], int(steps))

    xs = line(settings.x_range_m, settings.xy_steps)
    ys = line(settings.y_range_m, settings.xy_steps)
    map_heights = np.asarray(settings.map_heights_m, dtype=float)
    heights = line(settings.height_range_m, settings.height_steps)
    tilts = line(settings.tilt_range_deg, settings.tilt_steps)
    yaws = line(settings.yaw_range_deg, settings.yaw_steps)
    level = np.eye(3)

    def rotation(roll_deg=0.0, pitch_deg=0.0, yaw_deg=0.0):
        return RollPitchYaw(np.radians([roll_deg, pitch_deg, yaw_deg])).ToRotationMatrix().matrix()

    return {
        "xy": ({"height_m": map_heights, "y_m": ys, "x_m": xs},
               [(np.array([x, y, h]), level) for h in map_heights for y in ys for x in xs]),
        "height": ({"height_m": heights}, [(np.array([0.0, 0.0, h]), level) for h in heights]),
        "tilt": ({"tilt_axis": np.array(["x", "y"]), "height_m": heights, "tilt_deg": tilts},
                 [(np.array([0.0, 0.0, h]), rotation(t, 0.0) if axis == "x" else rotation(0.0, t))
                  for axis in ("x", "y") for h in heights for t in tilts]),
        "yaw": ({"height_m": heights, "yaw_deg": yaws},
                [(np.array([0.0, 0.0, h]), rotation(yaw_deg=yaw))
                 for h in heights for yaw in yaws]),
    }


def _stack(per_pose: list, shape: tuple):
    """The per-pose metric dicts as one dict of the same keys holding arrays of ``shape``."""
    first = per_pose[0]
    if isinstance(first, dict):
        return {key: _stack([m[key] for m in per_pose], shape) for key in first}
    return np.asarray(per_pose, dtype=float).reshape(shape)


def _finite_range(values) -> dict:
    finite = np.asarray(values, dtype=float)
    finite = finite[np.isfinite(finite)]
    if finite.size == 0:
        return {"min": math.nan, "max": math.nan}
    return {"min": float(finite.min()), "max": float(finite.max())}


def _per_height(maps: np.ndarray, centre: tuple) -> dict:
    """min, median and max over each height's x-y grid points where the value is
    finite, and the value at the grid point nearest the centre; lists, one per height."""
    def over(reduce):
        return [float(reduce(m[np.isfinite(m)])) if np.isfinite(m).any() else math.nan
                for m in maps]
    return {"min": over(np.min), "median": over(np.median), "max": over(np.max),
            "centre": [float(m[centre]) for m in maps]}


def _summary(config: DeviceConfig, magnetics: MagneticsModel, slices: dict) -> dict:
    """Headline numbers of one instrument's slices (SI units; see the keys)."""
    xy = slices["xy"]
    maps = xy["maps"]
    centre = (int(np.argmin(np.abs(xy["coordinates"]["y_m"]))),
              int(np.argmin(np.abs(xy["coordinates"]["x_m"]))))
    ceilings = {}
    for limit in LIMIT_KINDS:
        _, upper = hover_workspace_A(config, coil_current_limit_a(config, limit), magnetics)
        ceilings[limit] = float(upper[2] + config.p_WA[2])
    worst = {"value": math.nan}
    for name, data in slices.items():
        condition = data["maps"]["condition_number"]
        if np.isfinite(condition).any() and not worst["value"] >= np.nanmax(condition):
            index = np.unravel_index(np.nanargmax(condition), condition.shape)
            worst = {"value": float(condition[index]), "slice": name,
                     "at": {axis: values[i].item()
                            for (axis, values), i in zip(data["coordinates"].items(), index)}}
    every = {key: np.concatenate([d["maps"][key].ravel() for d in slices.values()])
             for key in ("hover_current_a", "hover_power_w", "condition_number")}
    return {
        # Highest level hover over the array centre, per current limit [m above W's z = 0].
        "hover_ceiling_m": ceilings,
        # Share of the x-y grid points, per map height, where the weight can be carried.
        "hover_fraction_xy": {
            limit: np.isfinite(maps["max_force_n"][limit]["+z"]).mean(axis=(1, 2)).tolist()
            for limit in LIMIT_KINDS},
        # Over every pose of every slice where the instrument hovers.
        "hover_current_a": _finite_range(every["hover_current_a"]),
        "hover_power_w": _finite_range(every["hover_power_w"]),
        "condition_number": {"best": _finite_range(every["condition_number"])["min"],
                             "worst": worst},
        # Per map height over the x-y grid (see _per_height): [A], [W], [N], [N m].
        "hover_current_xy_a": _per_height(maps["hover_current_a"], centre),
        "hover_power_xy_w": _per_height(maps["hover_power_w"], centre),
        "max_force_xy_n": {limit: {d: _per_height(maps["max_force_n"][limit][d], centre)
                                   for d in DIRECTIONS} for limit in LIMIT_KINDS},
        "max_torque_xy_nm": {limit: {d: _per_height(maps["max_torque_nm"][limit][d], centre)
                                     for d in DIRECTIONS} for limit in LIMIT_KINDS},
    }


def _json_ready(value):
    """Arrays to lists, numpy scalars to floats, NaN and infinities to None."""
    if isinstance(value, dict):
        return {key: _json_ready(item) for key, item in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_json_ready(item) for item in (value.tolist() if isinstance(value, np.ndarray)
                                               else value)]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def slice_metrics(job) -> list:
    """``pose_metrics`` at each pose of ``job`` = (device config, [(p_WI, R_WI)])."""
    config, poses = job
    magnetics = load_magnetics(config)
    return [pose_metrics(magnetics, config, p_WI, R_WI) for p_WI, R_WI in poses]


def workspace_study(settings: WorkspaceSettings, *, device: DeviceConfig | None = None,
                    progress: Callable[[int, int], None] | None = None, workers: int = 1,
                    scheduler: str | None = None) -> dict:
    """The study (module docstring) over ``settings``' grids, as JSON-ready data.

    Returns {"study", "settings", "units", "instruments": {kind: {"mass_kg",
    "lever_length_m", "current_limit_a": {limit: A}, "summary", "slices":
    {name: {"coordinates": {axis: values}, "maps": {metric: nested lists}}}}}}.
    Each map's nesting follows its slice's coordinates in order (e.g. xy:
    [height][y][x]); metrics are those of ``pose_metrics``. NaN is None.
    ``progress(n_done, n_total)``, if given, is called after every slice. Each
    instrument's slice is a job (``analysis/parallel.py``: ``workers``, ``scheduler``).
    ``device``: the coils, amplifiers and thermal model to use (a scenario's); its
    own instrument keeps its magnet and mass overrides, the other kind its defaults.
    """
    settings.check()
    slice_grids = _slices(settings)
    base = device if device is not None else DeviceConfig()
    configs = {kind: (dataclasses.replace(base, instrument=kind) if kind == base.instrument else
                      dataclasses.replace(base, instrument=kind, magnet=None,
                                          instrument_mass_kg=None))
               for kind in settings.instruments}
    jobs = [(configs[kind], poses) for kind in settings.instruments
            for _, poses in slice_grids.values()]
    per_slice = iter(map_jobs(slice_metrics, jobs, workers=workers, scheduler=scheduler,
                              description="workspace slices", progress=False,
                              on_result=progress).results)
    instruments = {}
    for kind, config in configs.items():
        slices = {}
        for name, (coordinates, _) in slice_grids.items():
            shape = tuple(len(values) for values in coordinates.values())
            slices[name] = {"coordinates": coordinates, "maps": _stack(next(per_slice), shape)}
        instruments[kind] = {
            "mass_kg": config.instrument_spec().mass_kg,
            "lever_length_m": lever_length_m(config),
            "current_limit_a": {limit: coil_current_limit_a(config, limit)
                                for limit in LIMIT_KINDS},
            "summary": _summary(config, load_magnetics(config), slices),
            "slices": slices,
        }
    return _json_ready({
        "study": "workspace",
        "settings": dataclasses.asdict(settings),
        "units": {"m": "positions, heights", "deg": "angles", "A": "currents", "W": "power",
                  "N": "forces", "N m": "torques (about I's origin, W axes)",
                  "condition_number": "of A with its torque rows divided by lever_length_m",
                  "null": "NaN: inside the glass, out of reach, or over the current limit"},
        "instruments": instruments,
    })


# --- plots ---------------------------------------------------------------------

_NAN_NOTE = "grey: cannot hover (out of reach, over the current limit, or inside the glass)"
_OVER_COLOUR = "magenta"


@dataclass
class _Panel:
    """One quantity to draw: its label with units, values, and colour scale."""

    label: str
    values: np.ndarray
    log: bool = False  # a ratio-like quantity: scale from its least value, log if over a decade
    limit: float | None = None  # top of the colour scale; larger values drawn magenta


def _array(values) -> np.ndarray:
    """JSON lists (None for NaN) as a float array."""
    return np.array(values, dtype=float)


def _title(kind: str) -> str:
    return kind.replace("_", "-") + " instrument"


def _weakest(maps: dict, directions) -> np.ndarray:
    """Elementwise minimum over ``directions`` of the per-direction maps."""
    return np.min([_array(maps[d]) for d in directions], axis=0)


def _colour_scale(panel: _Panel):
    """(norm, colour map, colour bar's extend) for ``panel``; NaN cells stay
    transparent over the axes' grey."""
    cmap = plt.get_cmap("viridis").with_extremes(over=_OVER_COLOUR)
    finite = panel.values[np.isfinite(panel.values)]
    if finite.size == 0:
        return plt.Normalize(0.0, 1.0), cmap, "neither"
    low, high = float(finite.min()), float(finite.max())
    extend = "neither"
    if panel.limit is not None and high > panel.limit:
        high, extend = panel.limit, "max"
    if panel.log and low > 0 and high > 10 * low:
        return LogNorm(low, high), cmap, extend
    if panel.log and high > low:
        return plt.Normalize(low, high), cmap, extend
    return plt.Normalize(0.0, max(high, 1e-12)), cmap, extend


def _colour_bar(fig, mesh, ax, panel: _Panel, extend: str) -> None:
    bar = fig.colorbar(mesh, ax=ax, label=panel.label, extend=extend, shrink=0.95)
    if isinstance(mesh.norm, LogNorm):
        # Plain numbers (3, 5, 10, 20) rather than 3 x 10^0.
        bar.ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 3.0, 5.0)))
        bar.ax.yaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
        bar.ax.yaxis.set_minor_formatter(NullFormatter())


def _xy_figure(kind: str, xy: dict, rows: list, heading: str, path: Path) -> Path:
    """Rows of x-y maps (each a _Panel of (n_heights, ny, nx) values), one column
    per height, one shared colour scale per row."""
    heights_mm = 1e3 * _array(xy["coordinates"]["height_m"])
    x_mm, y_mm = 1e3 * _array(xy["coordinates"]["x_m"]), 1e3 * _array(xy["coordinates"]["y_m"])
    device = DeviceConfig(instrument=kind)
    centres_mm = 1e3 * device.array.coil_positions_A()[:, :2]
    radius_mm = 1e3 * device.coil.outer_diameter_m / 2
    half_range_mm = 1e3 * PAPER_RANGE_M / 2
    pad_mm = (x_mm[-1] - x_mm[0]) / max(len(x_mm) - 1, 1) / 2
    n_cols = len(heights_mm)
    fig, axes = plt.subplots(len(rows), n_cols, figsize=(3.4 * n_cols + 2.2, 3.2 * len(rows) + 0.6),
                             sharex=True, sharey=True, squeeze=False, layout="constrained")
    for row, panel in enumerate(rows):
        norm, cmap, extend = _colour_scale(panel)
        for col in range(n_cols):
            ax = axes[row, col]
            ax.set_facecolor("0.85")
            mesh = ax.pcolormesh(x_mm, y_mm, panel.values[col], shading="nearest", cmap=cmap,
                                 norm=norm)
            for centre in centres_mm:
                ax.add_patch(Circle(centre, radius_mm, fill=False, lw=0.4, color="w", alpha=0.6))
            ax.add_patch(Rectangle((-half_range_mm, -half_range_mm), 2 * half_range_mm,
                                   2 * half_range_mm, fill=False, ls="--", lw=0.8, color="tab:red"))
            ax.set_aspect("equal")
            ax.set_xlim(x_mm[0] - pad_mm, x_mm[-1] + pad_mm)
            ax.set_ylim(y_mm[0] - pad_mm, y_mm[-1] + pad_mm)
            if row == 0:
                ax.set_title(f"height of I {heights_mm[col]:.0f} mm")
            ax.set_xlabel("x [mm]")
            ax.set_ylabel("y [mm]")
            ax.label_outer()
        _colour_bar(fig, mesh, axes[row, :], panel, extend)
    fig.suptitle(f"{_title(kind)}: {heading}\nlevel, yaw 0; white circles: coils; red dashed: "
                 f"the paper's 100 x 100 mm range\n{_NAN_NOTE}", fontsize=10)
    return save_figure(fig, path, dpi=90, tight=False)


def _tilt_figure(kind: str, tilt: dict, panels, path: Path) -> Path:
    """Heat maps over (tilt, height), one row per tilt axis; ``panels(maps)``
    gives the row's _Panels of (n_heights, n_tilts) values."""
    tilts = _array(tilt["coordinates"]["tilt_deg"])
    heights_mm = 1e3 * _array(tilt["coordinates"]["height_m"])
    axes_names = tilt["coordinates"]["tilt_axis"]
    rows = [panels({key: _index(value, i) for key, value in tilt["maps"].items()})
            for i in range(len(axes_names))]
    fig, axes = plt.subplots(len(rows), len(rows[0]), figsize=(4.2 * len(rows[0]), 3.4 * len(rows)),
                             squeeze=False, layout="constrained")
    for row, (axis, row_panels) in enumerate(zip(axes_names, rows)):
        for col, panel in enumerate(row_panels):
            ax = axes[row, col]
            ax.set_facecolor("0.85")
            norm, cmap, extend = _colour_scale(panel)
            mesh = ax.pcolormesh(tilts, heights_mm, panel.values, shading="nearest", cmap=cmap,
                                 norm=norm)
            _colour_bar(fig, mesh, ax, panel, extend)
            ax.set_title(f"tilted about W's {axis}", fontsize=9)
            ax.set_xlabel(f"tilt about {axis} [deg]")
            if col == 0:
                ax.set_ylabel("height of I above the glass [mm]")
    fig.suptitle(f"{_title(kind)}: tilted over the array centre, yaw 0\n{_NAN_NOTE}; "
                 f"{_OVER_COLOUR}: hover current over the peak limit", fontsize=10)
    return save_figure(fig, path, dpi=90, tight=False)


def _yaw_figure(kind: str, yaw: dict, panels, path: Path, n_lines: int = 5) -> Path:
    """Lines versus yaw, one per height (up to ``n_lines`` of the heights where
    the instrument hovers); ``panels(maps)`` gives _Panels of (n_heights, n_yaws)."""
    yaws = _array(yaw["coordinates"]["yaw_deg"])
    heights_mm = 1e3 * _array(yaw["coordinates"]["height_m"])
    row_panels = panels(yaw["maps"])
    hovering = np.flatnonzero(np.isfinite(row_panels[1].values).any(axis=1))
    chosen = hovering[np.unique(np.linspace(0, len(hovering) - 1, min(n_lines, len(hovering)))
                                .round().astype(int))] if len(hovering) else hovering
    colours = plt.get_cmap("plasma")(np.linspace(0.0, 0.85, max(len(chosen), 1)))
    fig, axes = plt.subplots(1, len(row_panels), figsize=(4.2 * len(row_panels), 4.0),
                             squeeze=False, layout="constrained")
    for ax, panel in zip(axes[0], row_panels):
        for colour, i in zip(colours, chosen):
            ax.plot(yaws, panel.values[i], color=colour, marker=".", ms=4,
                    label=f"height {heights_mm[i]:.1f} mm")
        if panel.limit is not None:
            ax.axhline(panel.limit, color="k", ls=":", lw=1, label="peak limit")
        top = np.nanmax(panel.values[chosen]) if np.isfinite(panel.values[chosen]).any() else 1.0
        ax.set_ylim(0.0, 1.1 * max(top, panel.limit or 0.0))
        ax.set_ylabel(panel.label)
        ax.set_xlabel("yaw [deg]")
        ax.grid(alpha=0.3)
    axes[0, 1].legend(fontsize=8)
    fig.suptitle(f"{_title(kind)}: level over the array centre, versus yaw "
                 "(no line or gaps: cannot hover within the limit)", fontsize=10)
    return save_figure(fig, path, dpi=90, tight=False)


def _height_figure(kind: str, data: dict, path: Path) -> Path:
    heights_mm = 1e3 * _array(data["slices"]["height"]["coordinates"]["height_m"])
    maps = data["slices"]["height"]["maps"]
    limits = data["current_limit_a"]
    fig, axes = plt.subplot_mosaic([["current", "current", "power", "power", "cond", "cond"],
                                    ["force", "force", "force", "torque", "torque", "torque"]],
                                   figsize=(14, 8.5), sharex=True, layout="constrained")
    ax = axes["current"]
    ax.plot(heights_mm, _array(maps["hover_current_a"]), color="tab:purple",
            label="minimum-norm allocation")
    ax.plot(heights_mm, _array(maps["hover_current_minmax_a"]), color="tab:purple", ls="--",
            label="best allocation (LP)")
    for limit, style in zip(LIMIT_KINDS, (":", "-.")):
        ax.axhline(limits[limit], color="k", ls=style, lw=1, label=f"{limit} limit")
    ax.set_ylabel("hover current, busiest coil [A]")
    ax.legend(fontsize=8)
    ax = axes["power"]
    ax.plot(heights_mm, _array(maps["hover_power_w"]), color="tab:orange")
    ax.set_ylabel("hover power at 20 C [W]\n(minimum-norm allocation)")
    ax = axes["cond"]
    ax.plot(heights_mm, _array(maps["condition_number"]), color="k")
    ax.set_ylabel("condition number of A\n(torque rows / lever length)")
    colours = {"x": "tab:red", "y": "tab:green", "z": "tab:blue"}
    for key, unit, scale, noun in (("max_force_n", "N", 1.0, "force along"),
                                   ("max_torque_nm", "N mm", 1e3, "torque about")):
        ax = axes["force" if key == "max_force_n" else "torque"]
        for direction in DIRECTIONS:
            style = "-" if direction[0] == "+" else "--"
            for limit, width in (("thermal", 2.0), ("peak", 0.8)):
                ax.plot(heights_mm, scale * _array(maps[key][limit][direction]),
                        color=colours[direction[1]], ls=style, lw=width,
                        label=f"{direction} {limit}")
        ax.set_ylabel(f"largest extra {noun} [{unit}]")
        ax.set_ylim(bottom=0.0)
        ax.legend(fontsize=7, ncol=2, loc="upper right",
                  title="thick: thermal limit, thin: peak", title_fontsize=7)
    for ax in axes.values():
        ax.grid(alpha=0.3)
        ax.tick_params(labelbottom=True)  # sharex hides them on the top row
        ax.set_xlabel("height of I above the glass [mm]")
    fig.suptitle(f"{_title(kind)}: level over the array centre, versus height\n"
                 "(gaps: inside the glass or cannot hover within that limit)", fontsize=10)
    return save_figure(fig, path, dpi=90, tight=False)


def _angle_panels(peak_a: float):
    def panels(maps: dict) -> list:
        thermal = maps["max_force_n"]["thermal"]
        return [
            _Panel("condition number of A", _array(maps["condition_number"]), log=True),
            _Panel("hover current, busiest coil [A]\n(minimum-norm allocation)",
                   _array(maps["hover_current_a"]), limit=peak_a),
            _Panel("extra force up, thermal limit [N]", _array(thermal["+z"])),
            _Panel("extra force sideways, thermal [N]\n(weakest of +-x, +-y)",
                   _weakest(thermal, ("+x", "-x", "+y", "-y"))),
        ]
    return panels


def plot_workspace(results: dict, out_dir: Path) -> list[Path]:
    """Write the study's PNG maps into ``out_dir`` (made if missing); return their paths.

    Per instrument: ``workspace_<kind>_xy_hover.png`` (condition number, hover
    current and power per map height), ``workspace_<kind>_xy_force_<limit>.png``
    (largest extra force up, down and in the weakest horizontal direction, and
    the weakest torque, per map height, within the peak or thermal limit),
    ``workspace_<kind>_height.png`` (profiles over the centre),
    ``workspace_<kind>_tilt.png`` (heat maps over tilt and height) and
    ``workspace_<kind>_yaw.png`` (lines versus yaw at several heights).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for kind, data in results["instruments"].items():
        maps = data["slices"]["xy"]["maps"]
        stem = f"workspace_{kind}"
        peak_a = data["current_limit_a"]["peak"]
        paths.append(_xy_figure(kind, data["slices"]["xy"], [
            _Panel("condition number of A\n(torque rows / lever length)",
                   _array(maps["condition_number"]), log=True),
            _Panel(f"hover current, busiest coil [A]\n(minimum-norm; magenta: > {peak_a:g} A peak)",
                   _array(maps["hover_current_a"]), limit=peak_a),
            _Panel("hover power at 20 C [W]\n(minimum-norm allocation)",
                   _array(maps["hover_power_w"]), log=True),
        ], "conditioning, hover current and power", out_dir / f"{stem}_xy_hover.png"))
        for limit in LIMIT_KINDS:
            force, torque = maps["max_force_n"][limit], maps["max_torque_nm"][limit]
            paths.append(_xy_figure(kind, data["slices"]["xy"], [
                _Panel("largest extra force up (+z) [N]", _array(force["+z"])),
                _Panel("largest extra force down (-z) [N]", _array(force["-z"])),
                _Panel("largest extra force sideways [N]\n(weakest of +-x, +-y)",
                       _weakest(force, ("+x", "-x", "+y", "-y"))),
                _Panel("largest extra torque [N mm]\n(weakest of the six)",
                       1e3 * _weakest(torque, DIRECTIONS)),
            ], f"largest extra force and torque within the {limit} current limit "
               f"({data['current_limit_a'][limit]:.2f} A a coil)",
                out_dir / f"{stem}_xy_force_{limit}.png"))
        paths.append(_height_figure(kind, data, out_dir / f"{stem}_height.png"))
        paths.append(_tilt_figure(kind, data["slices"]["tilt"], _angle_panels(peak_a),
                                  out_dir / f"{stem}_tilt.png"))
        paths.append(_yaw_figure(kind, data["slices"]["yaw"], _angle_panels(peak_a),
                                 out_dir / f"{stem}_yaw.png"))
    return paths


def _index(value, i):
    """value[i] through the nested metric dicts (the tilt slice's axis i)."""
    if isinstance(value, dict):
        return {key: _index(item, i) for key, item in value.items()}
    return value[i]
