"""Device description, electromagnetic model, and (later) hardware drivers."""

from maglev_haptics.hardware.device import (  # noqa: F401
    AmplifierSpec, CoilArraySpec, CoilSpec, DeviceConfig, DisplaySpec,
    InstrumentSpec, MagnetSpec, TrackerSpec, default_instrument,
)
from maglev_haptics.hardware.magnetics import MagneticsModel, load_magnetics  # noqa: F401,E402
