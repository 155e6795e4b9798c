"""docs/architecture.md's lists stay true: the station's ports against the stations
built (simulated, and on LCM over an in-memory bus), the scenario's YAML tags
against the schema. A port or tag added to the code and not to the page, or listed
on the page and absent from the code, fails here."""

import dataclasses
import typing
from pathlib import Path
from typing import Union

import pytest
from pydrake.common import pretty_class_name

from maglev_haptics.diagrams.lcm_station import INBOUND_PORTS, LcmStation
from maglev_haptics.diagrams.scenario import Scenario, load_scenario, with_stereo
from maglev_haptics.diagrams.station import MakeStation
from maglev_haptics.hardware import load_magnetics

ARCHITECTURE = Path(__file__).resolve().parents[1] / "docs" / "architecture.md"
# The 'present' column's values: when a port exists, from what the scenario holds.
PRESENT = {"always": lambda s: True,
           "with a hand": lambda s: s.hand is not None,
           "with the stereo display": lambda s: s.stereo is not None,
           "with the stereo display and no haptic scene":
               lambda s: s.stereo is not None and s.haptics is None,
           "on a calibration flight": lambda s: s.calibration is not None}


def station_diagram(scenario: Scenario):
    """The station Diagram built for ``scenario`` (simulated, or over LCM with an
    LcmStation: building it sends and waits for nothing). The one place in this file
    that knows how a station is built."""
    return MakeStation(scenario, magnetics=load_magnetics(scenario.device)).system


def on_lcm(scenario: Scenario) -> Scenario:
    """``scenario`` with its station on LCM, over an in-memory bus."""
    return dataclasses.replace(scenario, station=LcmStation(
        url="memq://", command_url="memq://", channel_prefix="DOCS_"))


def table_rows(marker: str):
    """The cells of each body row of the Markdown table between ``<!-- marker -->`` and
    ``<!-- /marker -->`` in docs/architecture.md, backticks stripped."""
    text = ARCHITECTURE.read_text()
    assert text.count(f"<!-- {marker} -->") == 1 and text.count(f"<!-- /{marker} -->") == 1
    block = text.split(f"<!-- {marker} -->")[1].split(f"<!-- /{marker} -->")[0]
    lines = [line for line in block.strip().splitlines() if line.startswith("|")][2:]
    assert lines, f"no table between <!-- {marker} --> and <!-- /{marker} -->"
    return [[cell.strip().strip("`") for cell in line.strip().strip("|").split("|")]
            for line in lines]


def port_rows():
    rows = table_rows("station ports")
    names = [row[0] for row in rows]
    assert len(names) == len(set(names)), f"a port listed twice: {names}"
    for name, direction, when, simulation_only, *_ in rows:
        assert direction in ("in", "out"), f"{name}: 'in / out' = {direction!r}"
        assert when in PRESENT, f"{name}: 'present' = {when!r}, not one of {list(PRESENT)}"
        assert simulation_only in ("yes", "no"), f"{name}: 'simulation only' = {simulation_only!r}"
    return rows


def documented_ports(scenario: Scenario, *, simulated: bool) -> set:
    """{(name, "in" | "out")} the page says ``scenario``'s station has."""
    return {(name, direction) for name, direction, when, simulation_only, *_ in port_rows()
            if PRESENT[when](scenario) and (simulated or simulation_only == "no")}


def built_ports(system) -> set:
    return ({(system.get_input_port(i).get_name(), "in") for i in range(system.num_input_ports())}
            | {(system.get_output_port(i).get_name(), "out")
               for i in range(system.num_output_ports())})


def shipped(name: str, label: str = None, *, stereo=False) -> Scenario:
    """A shipped scenario; ``stereo``: True with the stereo display, "calibration" as a
    calibration flight."""
    scenario = load_scenario(name, label, "{calibration: {flight: holds}}"
                             if stereo == "calibration" else "{}")
    return with_stereo(scenario, label or name) if stereo is True else scenario


# Together they meet every 'present' condition: none; a hand and a haptic scene; the
# stereo display with no scene; the stereo display with a scene.
SIMULATED = [("levitate", None, False), ("peg_in_hole", None, False),
             ("stereo_display", "head_sweep", False), ("peg_in_hole", None, True),
             ("levitate", None, "calibration")]
# On LCM the stereo display needs a haptic scene.
ON_LCM = [("levitate", None, False), ("peg_in_hole", None, False),
          ("peg_in_hole", None, True), ("levitate", None, "calibration")]


def case_id(case) -> str:
    name, label, extra = case
    return (label or name) + {False: "", True: "+stereo", "calibration": "+calibration"}[extra]


@pytest.mark.parametrize("case", SIMULATED, ids=case_id)
def test_the_simulated_stations_ports_are_the_documented_ones(case):
    name, label, stereo = case
    scenario = shipped(name, label, stereo=stereo)
    assert built_ports(station_diagram(scenario)) == documented_ports(scenario, simulated=True)


@pytest.mark.parametrize("case", ON_LCM, ids=case_id)
def test_the_lcm_stations_ports_are_the_documented_ones_less_the_simulations(case):
    name, label, stereo = case
    scenario = on_lcm(shipped(name, label, stereo=stereo))
    assert built_ports(station_diagram(scenario)) == documented_ports(scenario, simulated=False)


def test_every_lcm_channels_port_is_documented_and_not_simulation_only():
    shared = {name for name, direction, _, simulation_only, *_ in port_rows()
              if direction == "out" and simulation_only == "no"}
    assert set(INBOUND_PORTS.values()) - {"lease"} <= shared  # the lease feeds no port


def variant_fields(schema, path: str = "") -> dict:
    """{field path: sorted YAML tags of its kinds} of every field of the dataclass
    ``schema``, nested ones too, that holds one of several dataclasses and so picks
    one by tag (``[]``: each item of a list, tuple or mapping). Drake's
    ``yaml_load_typed`` matches a tag to a Union member's ``pretty_class_name``."""
    fields = {}

    def walk(hint, where):
        origin, args = typing.get_origin(hint), typing.get_args(hint)
        if origin is Union:
            members = [a for a in args if a is not type(None)]
            kinds = [a for a in members if dataclasses.is_dataclass(a)]
            if len(kinds) > 1:
                fields[where] = sorted("!" + pretty_class_name(kind) for kind in kinds)
            for member in members:
                walk(member, where)
        elif origin in (list, tuple, dict, set, frozenset):
            for arg in (args[1:] if origin is dict else args):
                if arg is not Ellipsis:
                    walk(arg, where + "[]")
        elif dataclasses.is_dataclass(hint):
            for name, field_hint in typing.get_type_hints(hint).items():
                walk(field_hint, f"{where}.{name}" if where else name)

    walk(schema, path)
    return fields


def test_the_documented_tags_are_the_schemas():
    rows = table_rows("scenario tags")
    fields = [field for field, _ in rows]
    assert len(fields) == len(set(fields)), f"a field listed twice: {fields}"
    documented = {field: sorted(tag.strip().strip("`") for tag in tags.split(","))
                  for field, tags in rows}
    assert documented == variant_fields(Scenario)
