"""The device and its physics: its description (coil array, instruments, amplifiers,
display, trackers), the electromagnetic model and its tables and kernels, the coils'
thermal model and the device's limits. ``link/``: what connects the application to a
device (the LCM messages and their checks, the lease, the drivers)."""

from maglev_haptics.hardware.device import (  # noqa: F401
    AmplifierSpec, CoilArraySpec, CoilSpec, DeviceConfig, DisplaySpec, GlassesSpec, HeadTrackerSpec,
    InstrumentSpec, MagnetSpec, ThermalSpec, TrackerSpec, default_instrument,
)
from maglev_haptics.hardware.limits import DeviceLimits, device_limits  # noqa: F401
from maglev_haptics.hardware.magnetics import MagneticsModel, load_magnetics  # noqa: F401
