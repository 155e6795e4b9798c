"""A leaf system behind C++ primitives: named ports, one Python call.

A Python output callback that reads one input and writes its output costs a tick
1.8 us in a diagram, whatever the arithmetic behind it; a C++ primitive in the
path 0.45 us (2026-11-27, ten of each added to a small loop). So a system on the
1 kHz path with many ports is a small diagram: its
named inputs stacked into one vector for the leaf that does the work in one
compiled call, and the leaf's one output vector split into the named outputs.
The diagram, the analysis and the tests see the same named ports as before.

A system whose state changes within a tick's output (a sample taken between two
ticks, an estimate released by a processing delay) holds that state in a C++
ZeroOrderHold fed back from its leaf's output (``BuildHeld``): the tick then costs
one Python output callback, with no Python update and no event between ticks.
"""

from typing import Dict, Sequence, Tuple

from pydrake.systems.framework import Diagram, DiagramBuilder, LeafSystem
from pydrake.systems.primitives import Demultiplexer, Multiplexer, ZeroOrderHold

Ports = Sequence[Tuple[str, int]]  # (name, size)


def stacked_size(ports: Ports) -> int:
    return sum(size for _, size in ports)


def stacked_slices(ports: Ports) -> Dict[str, slice]:
    """Each port's rows in the stacked vector, by name."""
    slices, start = {}, 0
    for name, size in ports:
        slices[name] = slice(start, start + size)
        start += size
    return slices


def _export_split(builder: DiagramBuilder, leaf: LeafSystem, outputs: Ports,
                  unexported_rows: int) -> None:
    """An "outputs" Demultiplexer on ``leaf``'s first output port, its ports exported by
    the names of ``outputs`` (the ``unexported_rows`` after them stay inside)."""
    split = builder.AddNamedSystem("outputs", Demultiplexer(
        [size for _, size in outputs] + ([unexported_rows] if unexported_rows else [])))
    builder.Connect(leaf.get_output_port(0), split.get_input_port())
    for i, (name, _) in enumerate(outputs):
        builder.ExportOutput(split.get_output_port(i), name)


def BuildStacked(diagram: Diagram, *, leaf: LeafSystem, leaf_name: str, inputs: Ports,
                 outputs: Ports, leaf_inputs: Sequence[str] = (),
                 leaf_outputs: Sequence[str] = (), unexported_rows: int = 0) -> None:
    """Build into ``diagram``: ``leaf`` (its first input port takes ``inputs`` stacked in
    order, its first output port gives ``outputs`` stacked in order, then
    ``unexported_rows`` more that stay inside: the rest of a state vector the port
    outputs whole) between an "inputs" Multiplexer and an "outputs" Demultiplexer
    whose ports are exported by name; then the leaf's own ports named in
    ``leaf_inputs`` and ``leaf_outputs``, as they are (an input that must not feed the
    stacked outputs through, an output of state)."""
    builder = DiagramBuilder()
    builder.AddNamedSystem(leaf_name, leaf)
    stack = builder.AddNamedSystem("inputs", Multiplexer([size for _, size in inputs]))
    for i, (name, _) in enumerate(inputs):
        builder.ExportInput(stack.get_input_port(i), name)
    builder.Connect(stack.get_output_port(), leaf.get_input_port(0))
    for name in leaf_inputs:
        builder.ExportInput(leaf.GetInputPort(name), name)
    _export_split(builder, leaf, outputs, unexported_rows)
    for name in leaf_outputs:
        builder.ExportOutput(leaf.GetOutputPort(name), name)
    builder.BuildInto(diagram)


def BuildHeld(diagram: Diagram, *, leaf: LeafSystem, leaf_name: str, period_s: float,
              outputs: Ports, unexported_rows: int = 0) -> None:
    """Build into ``diagram``: ``leaf``, whose first output port (``outputs`` stacked in
    order, then ``unexported_rows`` more) is its whole state, and whose input port
    "held" reads that output as a ZeroOrderHold ("hold", every ``period_s`` s) took it
    at the last tick (zeros before the first: the leaf reads a zero record as its
    initial state); an "outputs" Demultiplexer exports the named outputs, and the
    leaf's other input ports are exported by their names."""
    builder = DiagramBuilder()
    builder.AddNamedSystem(leaf_name, leaf)
    size = stacked_size(outputs) + unexported_rows
    hold = builder.AddNamedSystem("hold", ZeroOrderHold(period_s, size))
    builder.Connect(leaf.get_output_port(0), hold.get_input_port())
    builder.Connect(hold.get_output_port(), leaf.GetInputPort("held"))
    for i in range(leaf.num_input_ports()):
        if leaf.get_input_port(i).get_name() != "held":
            builder.ExportInput(leaf.get_input_port(i), leaf.get_input_port(i).get_name())
    _export_split(builder, leaf, outputs, unexported_rows)
    builder.BuildInto(diagram)
