"""The scenario's whole loop, linearized: the Jacobian of its state map over one
hyperperiod at an operating point, from the very diagram ``maglev run`` simulates
(station with the hand, tracker, estimator, controller, allocator, coupling, scene).

- ``linearize``: the single-rate loop (the tracker at the control rate, as the
  scenario switch ``control_rate_hz: 860`` does the other way round);
- ``multirate``: the true loop (an 860 Hz tracker against a 1 kHz controller:
  a 50 ms hyperperiod), compared with the single-rate one over the same time.

The map comes from central differences: the loop's systems are float-only compiled
kernels (one numeric strategy, no AutoDiffXd), and ``linearization.py``'s tests check
the differences once against AutoDiff and a hand derivation on a 1-DOF loop built
from Drake's own systems. States
that only record or display (the logger's hold, the stereo display) feed nothing
back and are left out; the coils' temperatures and the device supervisor's fault
mode are held.
"""

import dataclasses
import math
import time
from fractions import Fraction
from pathlib import Path
from typing import Callable, Dict, List, Optional

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from maglev_haptics.analysis.run_plots import save_figure  # noqa: E402

from pydrake.multibody.plant import MultibodyPlant  # noqa: E402

from pydrake.systems.analysis import Simulator  # noqa: E402

from maglev_haptics.analysis.linearization import (  # noqa: E402
    MAX_DENOMINATOR, difference_step, hyperperiod_s, leaf_systems, modes, monodromy_central,
    nudged, state_after, state_names, state_vector)
from maglev_haptics.analysis.loop_studies import StudyNotApplicable  # noqa: E402
from maglev_haptics.diagrams.application import BuildDiagram, RunMode  # noqa: E402
from maglev_haptics.diagrams.hand_script import ScriptedHand, hand_plan  # noqa: E402
from maglev_haptics.diagrams.haptics import stepped_in_place  # noqa: E402
from maglev_haptics.diagrams.station import hand_start_pose  # noqa: E402
from maglev_haptics.systems.pose_estimator import CLOCK_ROWS  # noqa: E402

# Systems whose states feed nothing back into the loop (name prefixes).
RECORDING_ONLY = ("station/head", "head_pose_predictor", "stereo_view")
# Held at the operating point: the coils' temperatures (a time constant of ~1 min,
# read only by the watchdogs) and the device supervisor's fault mode.
HELD_STATES = ("coil_temperatures", "device_supervisor")
# Discrete modes, compared exactly (a nudge would switch the mode): held, as the
# linearization is about a fixed mode.
MODE_COORDINATES = ("haptic_supervisor/law[0]",)
# The tracker's and the estimator's sample clocks (which sample is the newest, which
# the estimator has processed): held, as a nudge would take or skip a sample.
SENSOR_PATH, ESTIMATOR_PATH = "station/marker_sensor", "pose_estimator"
SETTLE_S = 0.3  # after haptics is fully on, before the operating point (s)
MODES_SHOWN = 12
HELD_TOLERANCE = 1e-6  # a row of the map this close to a unit vector is a held state
NEUTRAL_TOLERANCE = 1e-4  # |multiplier| this close to 1 over the period: a neutral mode


def check_applies(scenario) -> None:
    """StudyNotApplicable for a loop whose state is too big for central differences."""
    from maglev_haptics.diagrams.deformable_scene import DeformableSurface
    from maglev_haptics.diagrams.scene import ModelScene
    from maglev_haptics.diagrams.scene_models import holds_tissue
    if scenario.haptics is None:
        return
    scene = scenario.haptics.scene
    if isinstance(scene, DeformableSurface):
        raise StudyNotApplicable(
            "its lattice has tens of thousands of states: central differences would take two "
            "runs per state; the lattice's own stability is max_stable_link_stiffness's "
            "(systems/lattice_dynamics.py), and the coupling's loop is in `passivity`, "
            "`zwidth` and `stability-map`")
    if isinstance(scene, ModelScene) and holds_tissue(scene.directives):
        raise StudyNotApplicable(
            "its tissue has thousands of states (each node's position and velocity): "
            "central differences would take two runs per state; the tissue's own stability "
            "is stable_substeps's (systems/tissue_fem.py), and the coupling's loop with the "
            "tissue's contact stiffness is in `passivity` and `zwidth`")


def operating_point_s(scenario) -> float:
    """A time (s) at which the loop holds still: haptics engaged and the scripted
    hand at rest for a hyperperiod and more (haptic scenes), or the middle of the
    first hover (levitation)."""
    if scenario.haptics is None:
        from maglev_haptics.diagrams.motion import flight_plan
        plan = flight_plan(scenario.motion, scenario.device.instrument_spec().rest_height_m)
        start, end = plan.holds[0]
        return 0.5 * (start + end)
    if not isinstance(scenario.hand, ScriptedHand):
        raise StudyNotApplicable(
            "its hand is driven from Meshcat: there is no scripted operating point")
    engaged = scenario.haptics.enable_at_s + scenario.haptics.coupling.ramp_s + SETTLE_S
    target, _ = hand_plan(scenario.hand, hand_start_pose(scenario))
    rate = target.derivative(1)
    for t in np.arange(engaged, target.end_time() - 0.2, 0.01):
        if all(np.abs(rate.value(t + dt)).max() < 1e-9 for dt in np.linspace(0, 0.2, 21)):
            return float(t)
    raise StudyNotApplicable("its scripted hand never rests for 0.2 s once haptics is on")


def _update_timings(diagram) -> Dict[str, tuple]:
    """Each leaf system with discrete state: its path -> (period, offset) of its
    periodic update (s, exact fractions)."""
    context = diagram.CreateDefaultContext()
    timings = {}
    for system in leaf_systems(diagram):
        path = "/".join(system.GetSystemPathname().split("::")[2:])
        if system.GetMyContextFromRoot(context).num_discrete_state_groups() == 0:
            continue
        attribute = system.GetUniquePeriodicDiscreteUpdateAttribute()
        if attribute is None:
            raise RuntimeError(f"{path}: no unique periodic update; its period is unknown")
        timings[path] = tuple(Fraction(value).limit_denominator(MAX_DENOMINATOR) for value
                              in (attribute.period_sec(), attribute.offset_sec()))
    return timings


def sample_clocks(diagram) -> tuple:
    """The state names of the tracker's and the estimator's sample clocks."""
    sensor = diagram.GetSubsystemByName("station").GetSubsystemByName("marker_sensor")
    return (tuple(f"{SENSOR_PATH}/hold[{row}]" for row in sensor.clock_rows)
            + tuple(f"{ESTIMATOR_PATH}/hold[{row}]" for row in CLOCK_ROWS))


def _periods(timings, kept_names) -> List[float]:
    """The update periods of the systems that own the kept states (s)."""
    return [float(period) for path, (period, _) in timings.items()
            if any(name.startswith((path + "[", path + "/")) for name in kept_names)]


def map_start_s(timings, near_s: float, hyperperiod: float) -> float:
    """Where the map starts (s): after the hyperperiod boundary at or before ``near_s``,
    half way to the first update after it. A simulator started there has no update
    due at its start, or within any rounding of it, so each nudged run does the
    same updates (exactly on the boundary, whether a fresh simulator redoes one at
    its start time hangs on the rounding of t / period, system by system: a 1 kHz
    loop at 5.4 s is 5400.000000000001 periods). Every phase of a periodic map
    has the same multipliers."""
    period = Fraction(hyperperiod).limit_denominator(MAX_DENOMINATOR)
    boundary = Fraction(near_s).limit_denominator(MAX_DENOMINATOR) // period * period
    first_update = min(offset + ((boundary - offset) // step + 1) * step
                       for step, offset in timings.values())
    return float((boundary + first_update) / 2)


def quaternion_coordinates(diagram) -> List[List[str]]:
    """The state names of each free body's quaternion, in every MultibodyPlant."""
    blocks = []
    for system in leaf_systems(diagram):
        if not isinstance(system, MultibodyPlant):
            continue
        path = "/".join(system.GetSystemPathname().split("::")[2:])
        names = system.GetStateNames(False)
        for index in system.GetFloatingBaseBodies():
            start = system.get_body(index).floating_positions_start()
            blocks.append([f"{path}/{names[start + k]}" for k in range(4)])
    return blocks


def reduce_map(M: np.ndarray, names: List[str], x0: np.ndarray, quaternions) -> Dict:
    """M without what is not dynamics at a fixed mode:
    - held coordinates (latched setpoints, stored poses: a row of M that is a unit
      vector), parameters of the operating point, each a multiplier of exactly 1;
    - the norm of each free body's quaternion, which the dynamics carry unchanged (a
      multiplier of exactly 1): its three tangent directions are kept.
    Returns the reduced map, its coordinate names and what was removed."""
    n = len(names)
    # Central differences leave ~1e-9 of noise on a unit row.
    held = [j for j in range(n) if np.max(np.abs(M[j] - np.eye(n)[j])) < HELD_TOLERANCE]
    index = {name: j for j, name in enumerate(names)}
    columns, reduced_names = [], []
    in_quaternion = {}
    for block in quaternions:
        if all(name in index for name in block):
            for name in block:
                in_quaternion[index[name]] = block
    done = set()
    for j in range(n):
        if j in held or j in done:
            continue
        if j in in_quaternion:
            block = [index[name] for name in in_quaternion[j]]
            q0 = x0[block] / np.linalg.norm(x0[block])
            # An orthonormal basis of the tangent space at q0 (the complement of q0).
            tangent = np.linalg.svd(np.eye(4) - np.outer(q0, q0))[0][:, 0:3]
            for k in range(3):
                column = np.zeros(n)
                column[block] = tangent[:, k]
                columns.append(column)
                reduced_names.append(f"{names[block[0]].rsplit('_', 1)[0]}_rotation{k}")
            done.update(block)
        else:
            column = np.zeros(n)
            column[j] = 1.0
            columns.append(column)
            reduced_names.append(names[j])
    T = np.array(columns).T  # reduced -> full coordinates, orthonormal columns
    return {"M": T.T @ M @ T, "names": reduced_names, "basis": T,
            "held": [names[j] for j in held],
            "quaternion_norms": len([b for b in quaternions if all(n_ in index for n_ in b)])}


def loop_map(scenario, *, progress: Optional[Callable[[int, int], None]] = None,
             operating_point_from=None) -> Dict:
    """The loop's hyperperiod map at the operating point, reduced (``reduce_map``): M,
    its state names, the hyperperiod, the operating point and how long it took.

    ``operating_point_from``: a scenario of the same diagram structure (other gains)
    whose simulation gives the operating point's state: an unstable loop's own
    simulation would have left the equilibrium before it is linearized there."""
    start = time.perf_counter()
    check_applies(scenario)
    t0 = operating_point_s(scenario)
    with_hand = isinstance(scenario.hand, ScriptedHand)
    built = BuildDiagram(stepped_in_place(scenario), mode=RunMode.LINEARIZE)
    names = state_names(built.diagram)
    held = MODE_COORDINATES + sample_clocks(built.diagram)
    kept = [i for i, name in enumerate(names)
            if not name.startswith(RECORDING_ONLY + HELD_STATES) and name not in held]
    kept_names = [names[i] for i in kept]
    timings = _update_timings(built.diagram)
    sensor = built.station.system.GetSubsystemByName("marker_sensor")
    period = hyperperiod_s(_periods(timings, kept_names) + [sensor.sample_period_s])
    t0 = map_start_s(timings, t0, period)
    if operating_point_from is None:
        context = _operating_context(built.diagram, t0)
    else:
        reference = BuildDiagram(stepped_in_place(operating_point_from), mode=RunMode.LINEARIZE)
        context = built.diagram.CreateDefaultContext()
        _fix_inputs(built.diagram, context)
        context.SetTimeStateAndParametersFrom(_operating_context(reference.diagram, t0))
    # A coordinate at +-inf (a "never yet" time stamp) cannot be nudged: held.
    x0 = state_vector(context)
    kept = [i for i in kept if np.isfinite(x0[i])]
    kept_names = [names[i] for i in kept]
    M = monodromy_central(built.diagram, context, period, progress=progress,
                          coordinates=kept)
    reduced = reduce_map(M, kept_names, state_vector(context)[kept],
                         quaternion_coordinates(built.diagram))
    result = {**reduced, "hyperperiod_s": period, "operating_point_s": t0}
    if with_hand:
        result.update(_input_output(built.diagram, context, period, kept, reduced["basis"]))
    result["wall_s"] = time.perf_counter() - start
    return result


def _fix_inputs(diagram, context) -> None:
    """Zero on every exported input (the hand target's offset)."""
    for i in range(diagram.num_input_ports()):
        diagram.get_input_port(i).FixValue(context, np.zeros(diagram.get_input_port(i).size()))


def _operating_context(diagram, t0: float):
    """The diagram's context simulated from its start to t0, its inputs at zero."""
    context = diagram.CreateDefaultContext()
    _fix_inputs(diagram, context)
    simulator = Simulator(diagram, context)
    simulator.Initialize()
    simulator.AdvanceTo(t0)
    return simulator.get_context()


def _input_output(diagram, context, period_s: float, kept: List[int], basis) -> Dict:
    """B, C, D of the loop at the operating point (reduced coordinates): input the
    hand target's position offset [x, y, z] (m), held over the period; output the
    wrench rendered on the hand [tau; f] (N m, N) at the period's start."""
    port = diagram.GetInputPort("hand_target_offset")
    controller = diagram.GetSubsystemByName("levitation_controller")
    output = controller.GetOutputPort("wrench_rendered_W")

    def rendered(trial):
        return output.Eval(controller.GetMyContextFromRoot(trial)).copy()

    x0 = state_vector(context)
    B = np.zeros((len(kept), 3))
    D = np.zeros((6, 3))
    step = 1e-6  # m of the hand target
    for k in range(3):
        ends, outputs = [], []
        for sign in (1.0, -1.0):
            trial = context.Clone()
            offset = np.zeros(port.size())
            offset[k] = sign * step
            port.FixValue(trial, offset)
            outputs.append(rendered(trial))
            ends.append(state_after(diagram, trial, period_s)[kept])
        B[:, k] = (ends[0] - ends[1]) / (2 * step)
        D[:, k] = (outputs[0] - outputs[1]) / (2 * step)
    C = np.zeros((6, len(kept)))
    for column, j in enumerate(kept):
        step_j = difference_step(x0[j])
        outputs = [rendered(nudged(context, x0, j, sign * step_j)) for sign in (1.0, -1.0)]
        C[:, column] = (outputs[0] - outputs[1]) / (2 * step_j)
    return {"B": basis.T @ B, "C": C @ basis, "D": D,
            "inputs": ["hand target x (m)", "hand target y (m)", "hand target z (m)"],
            "outputs": ["rendered torque x (N m)", "rendered torque y (N m)",
                        "rendered torque z (N m)", "rendered force x (N)",
                        "rendered force y (N)", "rendered force z (N)"]}


def _mode_rows(M, period_s, names) -> List[Dict]:
    rows = []
    for mode in modes(M, period_s, names)[:MODES_SHOWN]:
        rows.append({"multiplier_abs": abs(mode.multiplier),
                     "multiplier_angle_rad": math.atan2(mode.multiplier.imag, mode.multiplier.real),
                     "frequency_hz": mode.frequency_hz, "damping_ratio": mode.damping_ratio,
                     "time_constant_s": mode.time_constant_s, "states": mode.states})
    return rows


def _radius(M) -> float:
    """The spectral radius without neutral multipliers (``stability``)."""
    return stability(M)["spectral_radius"]


def stability(M, names=None, period_s=None) -> Dict:
    """Spectral radius of the map without its neutral multipliers (within
    NEUTRAL_TOLERANCE of the unit circle: symmetries such as a ball's orientation,
    which nothing in the scene depends on), and those neutral modes. Stable: every
    other multiplier inside the unit circle, none outside it."""
    values = np.linalg.eigvals(M) if len(M) else np.zeros(0)
    magnitudes = np.abs(values)
    neutral = np.abs(magnitudes - 1.0) < NEUTRAL_TOLERANCE
    rest = magnitudes[~neutral]
    result = {"spectral_radius": float(rest.max()) if len(rest) else 0.0,
              "neutral_multipliers": int(neutral.sum())}
    result["stable"] = bool(result["spectral_radius"] < 1.0)
    if names is not None and neutral.any():
        result["neutral_modes"] = [m.states for m in modes(M, period_s, names)
                                   if abs(abs(m.multiplier) - 1.0) < NEUTRAL_TOLERANCE]
    return result


def single_rate(scenario):
    """The scenario with its tracker at the control rate (one loop rate)."""
    tracker = dataclasses.replace(scenario.device.tracker, rate_hz=scenario.control_rate_hz)
    return dataclasses.replace(scenario, device=dataclasses.replace(scenario.device,
                                                                    tracker=tracker))


def linearize_study(scenario, progress=None) -> Dict:
    """The single-rate loop's map over its hyperperiod, its spectral radius and modes."""
    result = loop_map(single_rate(scenario), progress=progress)
    M, period = result["M"], result["hyperperiod_s"]
    return {"operating_point_s": result["operating_point_s"], "period_s": period,
            "states": result["names"], "A": M.tolist(),
            **{key: result[key].tolist() if hasattr(result.get(key), "tolist") else result[key]
               for key in ("B", "C", "D", "inputs", "outputs") if key in result},
            **stability(M, result["names"], period), "held_states": result["held"],
            "modes": _mode_rows(M, period, result["names"]),
            "wall_s": result["wall_s"],
            "note": ("A maps the whole state (every system's discrete state, the logger's "
                     "excepted) over one period at the operating point; held states (latched "
                     "setpoints, timers) are taken out, and each quaternion is reduced to its "
                     f"three rotations. Modes above {0.5 / period:g} Hz alias in frequency "
                     "(their decay is exact). The spectral radius leaves neutral modes out.")}


def multirate_study(scenario, progress=None) -> Dict:
    """The true multirate loop's monodromy, against the single-rate loop over the same
    time (its map raised to the power that spans the multirate hyperperiod)."""
    true = loop_map(scenario, progress=progress)
    single = loop_map(single_rate(scenario))
    M, period = true["M"], true["hyperperiod_s"]
    steps = round(period / single["hyperperiod_s"])
    single_radius_over_period = _radius(single["M"]) ** steps
    return {"operating_point_s": true["operating_point_s"], "hyperperiod_s": period,
            "states": true["names"], **stability(M, true["names"], period),
            # The slowest mode's amplitude one second on, per unit now: the spectral
            # radius over a second (a factor, not a rate).
            "held_states": true["held"],
            "slowest_mode_left_after_1_s": _radius(M) ** (1.0 / period),
            "single_rate": {"hyperperiod_s": single["hyperperiod_s"],
                            "periods_per_hyperperiod": steps,
                            "spectral_radius": _radius(single["M"]),
                            "spectral_radius_over_multirate_hyperperiod":
                                single_radius_over_period,
                            "slowest_mode_left_after_1_s":
                                _radius(single["M"]) ** (1.0 / single["hyperperiod_s"])},
            "modes": _mode_rows(M, period, true["names"]),
            "single_rate_modes": _mode_rows(single["M"], single["hyperperiod_s"], single["names"]),
            "wall_s": true["wall_s"] + single["wall_s"],
            "multiplier_magnitudes": sorted(np.abs(np.linalg.eigvals(M)).tolist(), reverse=True),
            "single_rate_magnitudes_over_hyperperiod": sorted(
                (np.abs(np.linalg.eigvals(single["M"])) ** steps).tolist(), reverse=True)}


def plot_multipliers(results: Dict, out_dir: Path, title: str, name: str) -> Path:
    """The map's eigenvalues in the unit circle (and the single-rate loop's, for the
    multirate study)."""
    figure, axes = plt.subplots(figsize=(6, 6))
    circle = np.linspace(0, 2 * np.pi, 400)
    axes.plot(np.cos(circle), np.sin(circle), color="0.6", lw=1)
    # The single-rate loop's multipliers over the multirate hyperperiod: raised to the
    # number of its periods in it.
    steps = results.get("single_rate", {}).get("periods_per_hyperperiod", 1)
    for label, rows, marker, power in (
            ("loop", results["modes"], "o", 1),
            ("single-rate loop, over the same time", results.get("single_rate_modes"), "x", steps)):
        if not rows:
            continue
        values = [(row["multiplier_abs"] * np.exp(1j * row["multiplier_angle_rad"])) ** power
                  for row in rows]
        axes.plot(np.real(values), np.imag(values), marker, ls="none", label=label)
    axes.set_aspect("equal")
    axes.set_xlabel("Re")
    axes.set_ylabel("Im")
    axes.set_title(f"{title}: {name}, spectral radius {results['spectral_radius']:.4f}")
    axes.legend(loc="lower left")
    return save_figure(figure, Path(out_dir) / f"{name}.png")
