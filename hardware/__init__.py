"""Device description, electromagnetic and thermal models, device limits (drivers later)."""

from maglev_haptics.hardware.device import (  # noqa: F401
    AmplifierSpec, CoilArraySpec, CoilSpec, DeviceConfig, DisplaySpec, GlassesSpec, HeadTrackerSpec,
    InstrumentSpec, MagnetSpec, ThermalSpec, TrackerSpec, default_instrument,
)
from maglev_haptics.hardware.limits import DeviceLimits, device_limits  # noqa: F401
from maglev_haptics.hardware.magnetics import MagneticsModel, load_magnetics  # noqa: F401
