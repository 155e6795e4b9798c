"""The scenario's schema and loading, the diagram's builders (the station, simulated or
on LCM; the application; scenes, haptics, the stereo display), the device simulator on
LCM, the device API, and the run: a scenario flown (``scenario_run.py``) by the
real-time runner (``runner.py``)."""
