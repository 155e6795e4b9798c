"""What the application and a run ask of a station, whatever it is.

``AddStation`` (``diagrams/station.py``) adds the scenario's station to a diagram and
returns a ``Station``: the simulated station, in the same diagram
(``SimulatedStation``), or the LCM interface to a device, ``maglev device-sim`` or a
real one (``LcmStationInterface``, ``diagrams/lcm_station.py``). Each knows what it
is and answers for itself what the builders and the run path need to know of it, so
none of them asks which kind it has:

- ``simulated``: its truth ports (``instrument_state``, ``hand_state``,
  ``hand_wrench_on_instrument_W``, ``head_pose``, ``query_object``) exist, for the
  simulation-only consumers (truth metrics, the station's Meshcat layer);
- ``keeps_wall_clock``: a device keeps the wall clock's time, so a run against it
  is paced (at 1.0 unless told);
- ``lands_before_run_end``: a flying instrument is landed before the run's time
  ends (a real one is not let fall; a simulated one's run may end anywhere);
- ``shares_cores``: another paced process (the device's) runs on this machine;
- ``measured_currents_lag_ticks``: how many ticks' commands the measured coil
  currents may follow, for the stuck-amplifier watchdog;
- ``watch(stop)``: the run's stop, with what the station itself stops a run for
  (a device gone silent);
- ``silence(context)``: how the device went silent (``device_silence``), or None
  while it is heard (always, for a simulated one);
- ``summary(context)``: its block of ``summary.json`` (``station``), or None;
- ``lease``: the application's end of the device's lease, or None.

Its Diagram, named ``station``, is ``system``; ``GetInputPort`` and
``GetOutputPort`` are that Diagram's (the ports ``diagrams/station.py`` lists).
"""

from typing import Callable, Optional

from pydrake.systems.framework import Diagram, InputPort, OutputPort


class Station:
    """A station in a diagram: its ``system`` and what it answers (module docstring).
    The subclasses set every answer."""

    simulated: bool
    keeps_wall_clock: bool
    lands_before_run_end: bool
    shares_cores: bool
    measured_currents_lag_ticks: int
    lease = None  # hardware.link.lease.LeaseClient, where there is a lease

    def __init__(self, system: Diagram):
        self.system = system

    def GetInputPort(self, name: str) -> InputPort:
        return self.system.GetInputPort(name)

    def GetOutputPort(self, name: str) -> OutputPort:
        return self.system.GetOutputPort(name)

    def watch(self, stop: Callable) -> Callable:
        """``simulate``'s ``stop``: ``stop(context)``, or True where the station itself
        ends the run."""
        return stop

    def silence(self, context) -> Optional[dict]:
        """How the device went silent by the root ``context``'s time, or None while it
        is heard (a simulated station always is)."""
        return None

    def summary(self, context) -> Optional[dict]:
        """Its block of summary.json at the root ``context``'s time, or None."""
        return None
