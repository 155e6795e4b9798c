"""Faults injected into the simulated station, as a scenario's ``faults`` list.

A dropped marker or a lost instrument is an ``occlusions`` entry and a hand that
lets go a grip event of its script; these are the rest of the fault campaign's
kinds (``maglev faults``):

- ``!LatencySpike``: from ``start_s`` to ``end_s`` no new sample arrives (the
  tracker's output holds its last one, ever staler), then they resume;
- ``!CorruptSample``: one coordinate of one marker of the sample at ``at_s`` is NaN
  (the rest of the sample is good);
- ``!StuckAmplifier``: from ``at_s`` on, coil ``coil``'s amplifier delivers zero, or
  its limit in one direction, whatever it is commanded;
- ``!Shove``: a force ``force_n`` (N, in W) on the instrument's centre of mass for
  ``duration_s`` from ``at_s`` (a push on the whole instrument; the same force at the
  magnets' centroid would also spin it about the magnet row, whose inertia is tiny).

Each is a plain dataclass the scenario loader fills; the station (diagrams/station.py)
builds the systems below, or passes the tracker's to the marker sensor, only for
the faults a scenario lists.
"""

import math
from dataclasses import dataclass, field
from typing import List, Sequence

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.plant import ExternallyAppliedSpatialForce
from pydrake.systems.framework import LeafSystem

from maglev_haptics.hardware.config_checks import nonnegative, positive, require, vector

STUCK_AT = ("zero", "positive_limit", "negative_limit")


@dataclass
class LatencySpike:
    start_s: float = 1.0  # (s)
    end_s: float = 1.03  # (s)

    def validate(self, path: str) -> None:
        nonnegative(f"{path}.start_s", self.start_s)
        require(math.isfinite(self.end_s) and self.end_s > self.start_s, f"{path}.end_s",
                self.end_s, f"must be finite and after start_s = {self.start_s}")


@dataclass
class CorruptSample:
    at_s: float = 1.0  # the sample nearest this time (s)
    marker: int = 0  # index into the instrument's markers
    coordinate: int = 0  # 0 x, 1 y, 2 z

    def validate(self, path: str, n_markers: int) -> None:
        nonnegative(f"{path}.at_s", self.at_s)
        require(self.marker in range(n_markers), f"{path}.marker", self.marker,
                f"must be a marker index 0..{n_markers - 1}")
        require(self.coordinate in range(3), f"{path}.coordinate", self.coordinate,
                "must be 0 (x), 1 (y) or 2 (z)")


@dataclass
class StuckAmplifier:
    coil: int = 0  # index into the coil array
    at_s: float = 1.0  # (s)
    stuck_at: str = "zero"  # "zero", "positive_limit" or "negative_limit" (the amplifier's)

    def validate(self, path: str, n_coils: int) -> None:
        require(self.coil in range(n_coils), f"{path}.coil", self.coil,
                f"must be a coil index 0..{n_coils - 1}")
        nonnegative(f"{path}.at_s", self.at_s)
        require(self.stuck_at in STUCK_AT, f"{path}.stuck_at", self.stuck_at,
                f"must be one of {', '.join(STUCK_AT)}")


@dataclass
class Shove:
    at_s: float = 1.0  # (s)
    duration_s: float = 0.01  # (s)
    force_n: List[float] = field(default_factory=lambda: [10.0, 0.0, 0.0])  # in W (N)

    def validate(self, path: str) -> None:
        nonnegative(f"{path}.at_s", self.at_s)
        positive(f"{path}.duration_s", self.duration_s)
        vector(f"{path}.force_n", self.force_n, 3)


def stalled(t_s: float, spikes: Sequence[LatencySpike]) -> bool:
    """Whether the tracker publishes nothing new at ``t_s`` (s)."""
    return any(spike.start_s <= t_s < spike.end_s for spike in spikes)


def corrupt(sample_index: int, p_WK: np.ndarray, corruptions: Sequence[CorruptSample],
            rate_hz: float) -> None:
    """NaN into the (3 n,) sample ``p_WK`` (m) of index round(t * rate_hz), in place,
    where a corruption falls on it."""
    for corruption in corruptions:
        if round(corruption.at_s * rate_hz) == sample_index:
            p_WK[3 * corruption.marker + corruption.coordinate] = np.nan


def stuck_currents(t_s: float, currents_a: np.ndarray, faults: Sequence[StuckAmplifier],
                   limit_a: float) -> np.ndarray:
    """The currents (A) the coils carry at ``t_s`` (s) when commanded ``currents_a``."""
    out = np.array(currents_a, dtype=float)
    for fault in faults:
        if t_s >= fault.at_s:
            out[fault.coil] = {"zero": 0.0, "positive_limit": limit_a,
                               "negative_limit": -limit_a}[fault.stuck_at]
    return out


class StuckAmplifiers(LeafSystem):
    """The amplifiers' currents with the stuck ones replaced (``stuck_currents``).

    .. pydrake_system::

        name: StuckAmplifiers
        input_ports:
        - coil_currents_commanded
        output_ports:
        - coil_currents_commanded_faulted
    """

    def __init__(self, faults: Sequence[StuckAmplifier], n_coils: int, limit_a: float):
        super().__init__()
        self._faults = list(faults)
        self._limit_a = float(limit_a)
        commanded = self.DeclareVectorInputPort("coil_currents_commanded", n_coils)
        self.DeclareVectorOutputPort(
            "coil_currents_commanded_faulted", n_coils,
            lambda context, output: output.SetFromVector(stuck_currents(
                context.get_time(), commanded.Eval(context), self._faults, self._limit_a)))


class Shoves(LeafSystem):
    """The shoves on the instrument's centre of mass (``p_BoBcm_B``, m, in the body's
    frame), for the plant's applied spatial force input.

    .. pydrake_system::

        name: Shoves
        output_ports:
        - spatial_forces
    """

    def __init__(self, shoves: Sequence[Shove], body_index, p_BoBcm_B):
        super().__init__()
        self._shoves = list(shoves)
        self._body_index = body_index
        self._p_BoBcm_B = np.asarray(p_BoBcm_B, dtype=float)
        self.DeclareAbstractOutputPort(
            "spatial_forces", lambda: AbstractValue.Make([ExternallyAppliedSpatialForce()]),
            self._calc)

    def _calc(self, context, output):
        t_s = context.get_time()
        forces = []
        for shove in self._shoves:
            if shove.at_s <= t_s < shove.at_s + shove.duration_s:
                force = ExternallyAppliedSpatialForce()
                force.body_index = self._body_index
                force.p_BoBq_B = self._p_BoBcm_B
                force.F_Bq_W = SpatialForce(np.zeros(3), np.asarray(shove.force_n, dtype=float))
                forces.append(force)
        output.set_value(forces)
