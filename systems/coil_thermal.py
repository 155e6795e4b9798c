"""The coils' winding temperatures from the currents that flow (station)."""

from __future__ import annotations

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from maglev_haptics.hardware.thermal import CoilThermal, step_temperatures_c, winding_numbers


class CoilTemperatures(LeafSystem):
    """Each coil's winding temperature (C), the thermal model's exact RC step
    (``hardware/thermal.py``) with each coil's current sampled once a period and held
    over it: exact for currents that change no faster (at 100 Hz, a sampled
    estimate of the 1 kHz currents; the time constant is ~1 min).

    .. pydrake_system::

        name: CoilTemperatures
        input_ports:
        - coil_currents
        output_ports:
        - coil_temperature_c

    Starts at ambient; the state is the output, so it holds between updates.
    """

    def __init__(self, *, model: CoilThermal, n_coils: int, period_s: float):
        super().__init__()
        self._numbers = winding_numbers(model, n_coils)
        self._period_s = float(period_s)
        self._currents = self.DeclareVectorInputPort("coil_currents", n_coils)
        self._temperature = self.DeclareDiscreteState(
            BasicVector(np.full(n_coils, model.ambient_c)))
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, 0.0, self._update)
        self.DeclareStateOutputPort("coil_temperature_c", self._temperature)

    def _update(self, context, discrete_state):
        # The update's state starts as a copy of the context's: stepped in place.
        step_temperatures_c(discrete_state.get_mutable_value(self._temperature),
                            self._currents.Eval(context), self._period_s, *self._numbers)
