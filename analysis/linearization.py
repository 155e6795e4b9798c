"""Linearizing a diagram's loop over a period: the Jacobian of the map that takes
the whole state at t0 to the state one period later (the monodromy matrix when
the period is the loop's hyperperiod). Stable iff its spectral radius is < 1.

Two ways to get it, the same map:
- central differences: the float diagram simulated from the state perturbed
  up and down along each coordinate (any diagram; randomness that is a pure
  function of the seed and the sample, as in the tracker, cancels). The loop's
  studies use these: its systems are float-only compiled kernels;
- AutoDiff: the diagram converted to AutoDiffXd and simulated from a state
  seeded with the identity (every system must support AutoDiffXd). It checks
  the differences once, on a 1-DOF loop of Drake's own systems
  (tests/test_linearization.py).

Abstract states (discrete modes, flags) are held as they are: the
linearization is about a fixed mode.
"""

import math
from dataclasses import dataclass
from fractions import Fraction
from typing import Callable, Iterable, List, Optional

import numpy as np
from pydrake.autodiffutils import AutoDiffXd, ExtractGradient, InitializeAutoDiff
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.analysis import InitializeParams, Simulator, Simulator_

# Central differences step, relative to each coordinate's magnitude with this floor
# (state units: m, rad, m/s, A, ...): the map's curvature error goes as the step
# squared, round-off as 1e-16 over the step.
RELATIVE_STEP = 1e-5
ABSOLUTE_STEP = 1e-6
# Periods and offsets (s) as exact fractions up to this denominator: 1/860 s is 1/860.
MAX_DENOMINATOR = 1_000_000


def hyperperiod_s(periods_s: Iterable[float], max_denominator: int = MAX_DENOMINATOR) -> float:
    """The least common multiple of sample periods (s), as exact fractions:
    1/860 and 1/1000 give 0.05 s."""
    fractions = [Fraction(p).limit_denominator(max_denominator) for p in periods_s]
    numerator = math.lcm(*(f.numerator * (math.lcm(*(g.denominator for g in fractions))
                                          // f.denominator) for f in fractions))
    return float(Fraction(numerator, math.lcm(*(f.denominator for f in fractions))))


def state_vector(context) -> np.ndarray:
    """The continuous state, then every discrete state group, as one vector."""
    parts = [context.get_continuous_state_vector().CopyToVector()]
    parts += [context.get_discrete_state(i).CopyToVector() for i in
              range(context.num_discrete_state_groups())]
    return np.concatenate(parts) if parts else np.zeros(0)


def set_state_vector(context, x) -> None:
    """Inverse of ``state_vector`` (x may hold float or AutoDiffXd)."""
    n = context.num_continuous_states()
    if n:
        context.SetContinuousState(x[0:n])
    start = n
    for i in range(context.num_discrete_state_groups()):
        size = context.get_discrete_state(i).size()
        context.SetDiscreteState(i, x[start:start + size])
        start += size


def state_names(diagram) -> List[str]:
    """A name for each coordinate of ``state_vector``: system path, then the
    continuous index or the discrete group and index."""
    context = diagram.CreateDefaultContext()
    continuous, discrete = [], []
    for system in leaf_systems(diagram):
        sub = system.GetMyContextFromRoot(context)
        # The path below the root diagram: "::root::station::plant" -> "station/plant".
        path = "/".join(system.GetSystemPathname().split("::")[2:])
        continuous += [f"{path}/x[{k}]" for k in range(sub.num_continuous_states())]
        if isinstance(system, MultibodyPlant) and sub.num_discrete_state_groups() == 1:
            # Its own names: body and coordinate ("instrument_qw", "hand_vx", ...).
            discrete += [f"{path}/{name}" for name in system.GetStateNames(False)]
            continue
        for group in range(sub.num_discrete_state_groups()):
            size = sub.get_discrete_state(group).size()
            discrete += [f"{path}/d{group}[{k}]" if sub.num_discrete_state_groups() > 1
                         else f"{path}[{k}]" for k in range(size)]
    names = continuous + discrete
    if len(names) != len(state_vector(context)):
        raise RuntimeError("state names do not cover the state vector")
    return names


def leaf_systems(diagram):
    """Every leaf system of ``diagram``, nested diagrams opened, in subsystem order."""
    for system in diagram.GetSystems():
        if hasattr(system, "GetSystems"):
            yield from leaf_systems(system)
        else:
            yield system


def _advance(simulator, context, duration_s: float, configure=None) -> None:
    if configure is not None:
        configure(simulator)
    simulator.Initialize(InitializeParams(suppress_initialization_events=True))
    simulator.AdvanceTo(context.get_time() + duration_s)


def state_after(diagram, context, duration_s: float, configure=None) -> np.ndarray:
    """``state_vector`` ``duration_s`` after ``context`` (which the run takes over)."""
    simulator = Simulator(diagram, context)
    _advance(simulator, context, duration_s, configure)
    return state_vector(simulator.get_context())


def nudged(context, x0: np.ndarray, index: int, step: float):
    """A clone of ``context`` whose state is ``x0`` with coordinate ``index`` moved by ``step``."""
    trial = context.Clone()
    x = x0.copy()
    x[index] += step
    set_state_vector(trial, x)
    return trial


def difference_step(value: float) -> float:
    """The central-difference step for a coordinate at ``value``."""
    return max(RELATIVE_STEP * abs(value), ABSOLUTE_STEP)


def monodromy_central(diagram, context, period_s: float,
                      progress: Optional[Callable[[int, int], None]] = None,
                      configure: Optional[Callable] = None,
                      coordinates: Optional[List[int]] = None) -> np.ndarray:
    """d x(t0 + period) / d x(t0) by central differences from ``context`` (at t0).
    ``configure(simulator)`` sets up each simulator (e.g. its integrator);
    ``coordinates``: only these state coordinates (rows and columns), e.g. without
    states that only record (a logger's hold) and feed nothing back."""
    x0 = state_vector(context)
    kept = list(range(len(x0))) if coordinates is None else list(coordinates)
    n = len(kept)
    M = np.zeros((n, n))
    for column, j in enumerate(kept):
        step = difference_step(x0[j])
        ends = [state_after(diagram, nudged(context, x0, j, sign * step), period_s, configure)[kept]
                for sign in (1.0, -1.0)]
        M[:, column] = (ends[0] - ends[1]) / (2 * step)
        if progress is not None:
            progress(column + 1, n)
    return M


def monodromy_autodiff(diagram, context, period_s: float,
                       configure: Optional[Callable] = None) -> np.ndarray:
    """d x(t0 + period) / d x(t0) by simulating the AutoDiffXd diagram; every system
    in it must convert (``ToAutoDiffXd``)."""
    diagram_ad = diagram.ToAutoDiffXd()
    context_ad = diagram_ad.CreateDefaultContext()
    context_ad.SetTimeStateAndParametersFrom(context)
    x0 = state_vector(context)
    set_state_vector(context_ad, InitializeAutoDiff(x0).ravel())
    simulator = Simulator_[AutoDiffXd](diagram_ad, context_ad)
    _advance(simulator, context_ad, period_s, configure)
    end = np.array(state_vector(simulator.get_context()), dtype=object).reshape(-1, 1)
    gradient = ExtractGradient(end)
    if gradient.shape[1] == 0:  # nothing depended on the state
        return np.zeros((len(x0), len(x0)))
    return gradient


@dataclass
class Mode:
    multiplier: complex  # eigenvalue of the map over period_s
    frequency_hz: float  # |Im s| / 2 pi, s = ln(multiplier) / period (aliased above 1/(2 period))
    damping_ratio: float  # -Re s / |s|
    time_constant_s: float  # -1 / Re s (inf for a marginal mode)
    states: List[str]  # the coordinates that carry most of the mode


def modes(M: np.ndarray, period_s: float, names: List[str], top: int = 3) -> List[Mode]:
    """The map's eigenvalues as continuous-time modes, largest multiplier first, each
    with the ``top`` states of largest participation factor |v_k w_k| (right and
    left eigenvector components: unlike the eigenvector alone, independent of the
    states' units)."""
    values, vectors = np.linalg.eig(M)
    left = np.linalg.pinv(vectors)
    order = np.argsort(-np.abs(values))
    result = []
    for index in order:
        mu = complex(values[index])
        if abs(mu) < 1e-12:
            s = complex(-math.inf, 0.0)
        else:
            s = complex(np.log(mu)) / period_s
        frequency = abs(s.imag) / (2 * math.pi) if math.isfinite(s.real) else 0.0
        magnitude = abs(s) if math.isfinite(s.real) else math.inf
        damping = -s.real / magnitude if magnitude and math.isfinite(magnitude) else 1.0
        time_constant = -1.0 / s.real if s.real < 0 and math.isfinite(s.real) else (
            0.0 if not math.isfinite(s.real) else math.inf)
        share = np.abs(vectors[:, index] * left[index, :])
        leading = [names[k] for k in np.argsort(-share)[:top]]
        result.append(Mode(mu, frequency, damping, time_constant, leading))
    return result
