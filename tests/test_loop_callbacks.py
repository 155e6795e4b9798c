"""The loop's thread split callback by callback as the loop runs: each callback's own
time, nested evaluations not counted twice, and the systems' classes untouched after."""

import pytest
from pydrake.systems.framework import DiagramBuilder, LeafSystem

from maglev_haptics.analysis.loop_callbacks import (
    CALLBACK_DECLARATIONS, CallbackClock, loop_callback_costs, timed_callbacks)

SOURCE_S, READER_S = 0.002, 0.004  # what each system's output spends of its own (s)


class FakeTime:
    """A clock that moves only when a calc spends time: exact, whatever the machine's load."""

    def __init__(self):
        self.t_s = 0.0

    def now(self) -> float:
        return self.t_s

    def spend(self, seconds: float) -> None:
        self.t_s += seconds


CLOCK = FakeTime()


class Source(LeafSystem):
    def __init__(self):
        LeafSystem.__init__(self)
        self.DeclareVectorOutputPort("y", 1, self._calc)

    def _calc(self, context, output):
        CLOCK.spend(SOURCE_S)
        output.SetAtIndex(0, context.get_time())


class Reader(LeafSystem):
    """Its output reads the source's inside its own calc, then spends its own time."""

    def __init__(self):
        LeafSystem.__init__(self)
        self._u = self.DeclareVectorInputPort("u", 1)
        self.DeclareVectorOutputPort("y", 1, calc=self._calc)

    def _calc(self, context, output):
        value = self._u.Eval(context)[0]
        CLOCK.spend(READER_S)
        output.SetAtIndex(0, value)


def test_each_callback_is_timed_less_the_callbacks_it_evaluated():
    clock = CallbackClock(now=CLOCK.now)
    with timed_callbacks(clock, modules=(__name__,)):
        builder = DiagramBuilder()
        source, reader = builder.AddSystem(Source()), builder.AddSystem(Reader())
        builder.Connect(source.get_output_port(), reader.get_input_port())
        diagram = builder.Build()
    assert not any(method in vars(cls) for cls in (Source, Reader)
                   for method in CALLBACK_DECLARATIONS)
    context = diagram.CreateDefaultContext()
    for k in range(10):
        context.SetTime(float(k))  # a new time: both outputs computed again
        reader.get_output_port().Eval(reader.GetMyContextFromRoot(context))
    assert clock.calls == {"Source._calc": 10, "Reader._calc": 10}
    assert clock.own_s["Source._calc"] == pytest.approx(10 * SOURCE_S, rel=1e-12)
    assert clock.own_s["Reader._calc"] == pytest.approx(10 * READER_S, rel=1e-12)


def test_the_levitation_loop_is_split_into_its_callbacks_and_the_rest():
    costs = loop_callback_costs("levitate", "takeoff_hover_land", warm_s=0.2,
                                duration_s=0.2)
    callbacks = costs["callbacks_us"]
    # The controller's law, the estimator, the magnetic force and the tracker run every
    # tick; the thermal model every tenth.
    for name in ("LevitationLaw._calc_command", "PoseEstimatorLaw._calc_record",
                 "MagneticActuation._calc_generalized_force", "MarkerSensorLaw._calc_record"):
        assert costs["calls_per_tick"][name] == pytest.approx(1.0)
        assert callbacks[name] > 0.0
    assert costs["calls_per_tick"]["CoilTemperatures._update"] == pytest.approx(0.1)
    assert 0.0 < costs["outside_callbacks_us"] < costs["tick_us"]
    assert list(callbacks.values()) == sorted(callbacks.values(), reverse=True)
