"""Where the loop's thread spends a tick, callback by callback, as the loop runs.

``maglev bench``'s per-system table times each system alone at hover, the best of
five: its code and data stay in the caches, and on a 2-core machine it read 2-8 times
less than the same callback costs in the running loop, where every tick passes
through every system. Here a scenario's diagram is built with each Python callback
of the project's systems timed, run free, and each tick split into the callbacks'
own time (a callback's time less that of the callbacks it evaluated: an output that
reads an input runs the upstream system's calc inside its own) and the rest: Drake's
framework and plants, and the C++ systems.

The callbacks are timed by wrapping them as they are declared: while the diagram is
built (``timed_callbacks``), every LeafSystem subclass of the package gets its own
``Declare*`` methods that wrap the callables passed to them, and loses them after.
The clock costs two ``perf_counter`` calls a callback (~0.2 us), counted in the
callbacks' time.
"""

from __future__ import annotations

import functools
import gc
import time
from collections import Counter, defaultdict
from contextlib import contextmanager
from typing import Callable, Dict, Iterator, Sequence

from pydrake.systems.framework import LeafSystem

from maglev_haptics.diagrams.application import BuildDiagram
from maglev_haptics.diagrams.runner import simulate
from maglev_haptics.diagrams.scenario import load_scenario

# The LeafSystem methods that take a callback our systems declare.
CALLBACK_DECLARATIONS = (
    "DeclareVectorOutputPort", "DeclareAbstractOutputPort", "DeclarePeriodicDiscreteUpdateEvent",
    "DeclarePeriodicPublishEvent", "DeclarePeriodicUnrestrictedUpdateEvent",
    "DeclareInitializationDiscreteUpdateEvent", "DeclareInitializationUnrestrictedUpdateEvent",
    "DeclareForcedPublishEvent", "DeclarePerStepPublishEvent")
PACKAGE = "maglev_haptics"


class CallbackClock:
    """Each wrapped callback's own time (s: its time less that of the wrapped callbacks
    it ran) and calls, by name ``Class.method``, on the clock ``now()`` (s)."""

    def __init__(self, now: Callable[[], float] = time.perf_counter):
        self._now = now
        self.own_s: Dict[str, float] = defaultdict(float)
        self.calls: Counter = Counter()
        self._nested_s = 0.0  # the wrapped callbacks run inside the one now running

    def reset(self) -> None:
        self.own_s.clear()
        self.calls.clear()

    def wrap(self, name: str, callback):
        @functools.wraps(callback)
        def timed(*args, **kwargs):
            outer_nested_s, self._nested_s = self._nested_s, 0.0
            start = self._now()
            try:
                return callback(*args, **kwargs)
            finally:
                elapsed_s = self._now() - start
                self.own_s[name] += elapsed_s - self._nested_s
                self.calls[name] += 1
                self._nested_s = outer_nested_s + elapsed_s
        return timed


def _subclasses(cls) -> Iterator[type]:
    for subclass in cls.__subclasses__():
        yield subclass
        yield from _subclasses(subclass)


def _timed_declaration(clock: CallbackClock, method: str):
    declare = getattr(LeafSystem, method)

    def declaration(self, *args, **kwargs):
        def timed(value):
            if callable(value) and not isinstance(value, type):
                return clock.wrap(f"{type(self).__name__}.{getattr(value, '__name__', 'calc')}",
                                  value)
            return value
        return declare(self, *map(timed, args), **{k: timed(v) for k, v in kwargs.items()})
    return declaration


@contextmanager
def timed_callbacks(clock: CallbackClock, modules: Sequence[str] = (PACKAGE,)):
    """Within it, the systems of ``modules`` (module name prefixes) constructed wrap
    their callbacks in ``clock``; their classes are as before after it."""
    patched = [cls for cls in set(_subclasses(LeafSystem))
               if LeafSystem in cls.__bases__ and cls.__module__.startswith(tuple(modules))]
    for cls in patched:
        for method in CALLBACK_DECLARATIONS:
            setattr(cls, method, _timed_declaration(clock, method))
    try:
        yield clock
    finally:
        for cls in patched:
            for method in CALLBACK_DECLARATIONS:
                delattr(cls, method)


def loop_callback_costs(file: str, name: str, *, warm_s: float = 1.0,
                        duration_s: float = 1.0) -> Dict:
    """Scenario ``name`` of ``file`` run free for ``warm_s`` then ``duration_s`` (s),
    its callbacks timed over the second stretch: the tick (us), each callback's own
    time a tick (us) and calls a tick, and the tick's time outside them (us)."""
    clock = CallbackClock()
    with timed_callbacks(clock):
        built = BuildDiagram(load_scenario(file, name))
    simulator, _, _ = simulate(built, warm_s, progress=False)
    ticks = duration_s / built.tick_s
    clock.reset()
    gc.disable()  # as simulate runs the loop
    try:
        start = time.perf_counter()
        simulator.AdvanceTo(warm_s + duration_s)
        wall_s = time.perf_counter() - start
    finally:
        gc.enable()
    callbacks_us = {key: 1e6 * seconds / ticks
                    for key, seconds in sorted(clock.own_s.items(), key=lambda kv: -kv[1])}
    tick_us = 1e6 * wall_s / ticks
    return {"tick_us": tick_us, "callbacks_us": callbacks_us,
            "calls_per_tick": {key: clock.calls[key] / ticks for key in callbacks_us},
            "outside_callbacks_us": tick_us - sum(callbacks_us.values())}
