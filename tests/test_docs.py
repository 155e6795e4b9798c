"""docs/architecture.md's lists stay true: the station's ports against the stations
built (simulated, and on LCM over an in-memory bus), the scenario's YAML tags
against the schema. A port or tag added to the code and not to the page, or listed
on the page and absent from the code, fails here."""

import dataclasses
import typing
from pathlib import Path
from typing import Union

import pytest

from maglev_haptics.diagrams.lcm_station import LcmStation
from maglev_haptics.diagrams.scenario import Scenario, load_scenario
from maglev_haptics.diagrams.station import MakeStation
from maglev_haptics.hardware import load_magnetics

ARCHITECTURE = Path(__file__).resolve().parents[1] / "docs" / "architecture.md"


def table_rows(marker: str):
    """The cells of each body row of the Markdown table between ``<!-- marker -->`` and
    ``<!-- /marker -->`` in docs/architecture.md, backticks stripped."""
    text = ARCHITECTURE.read_text()
    block = text.split(f"<!-- {marker} -->")[1].split(f"<!-- /{marker} -->")[0]
    lines = [line for line in block.strip().splitlines() if line.startswith("|")][2:]
    return [[cell.strip().strip("`") for cell in line.strip("|").split("|")] for line in lines]


def documented_ports(*, hand: bool, stereo: bool, haptics: bool, simulated: bool):
    """{(name, "in" | "out")} the page says a station has."""
    present = {"always": True, "with a hand": hand, "with the stereo display": stereo,
               "with the stereo display and no haptic scene": stereo and not haptics}
    ports = set()
    for name, direction, when, simulation_only, _ in table_rows("station ports"):
        assert when in present, f"{name}: 'present' = {when!r}, not one of {list(present)}"
        if present[when] and (simulated or simulation_only == "no"):
            ports.add((name, direction))
    return ports


def built_ports(station) -> set:
    system = station.system
    return ({(system.get_input_port(i).get_name(), "in") for i in range(system.num_input_ports())}
            | {(system.get_output_port(i).get_name(), "out")
               for i in range(system.num_output_ports())})


@pytest.mark.parametrize("name", [("levitate",), ("peg_in_hole",),
                                  ("stereo_display", "head_sweep")])
def test_the_simulated_stations_ports_are_the_documented_ones(name):
    scenario = load_scenario(*name)
    station = MakeStation(scenario, magnetics=load_magnetics(scenario.device))
    assert built_ports(station) == documented_ports(
        hand=scenario.hand is not None, stereo=scenario.stereo is not None,
        haptics=scenario.haptics is not None, simulated=True)


@pytest.mark.parametrize("name", ["levitate", "peg_in_hole"])
def test_the_lcm_stations_ports_are_the_documented_ones_less_the_simulations(name):
    scenario = dataclasses.replace(load_scenario(name), station=LcmStation(
        url="memq://", command_url="memq://", channel_prefix="DOCS_"))
    station = MakeStation(scenario, magnetics=load_magnetics(scenario.device))  # sends nothing
    assert built_ports(station) == documented_ports(
        hand=scenario.hand is not None, stereo=False,
        haptics=scenario.haptics is not None, simulated=False)


def variant_fields(schema, path: str = "") -> dict:
    """{field path: [its kinds' tags]} of every field of the dataclass ``schema``, nested
    ones too, that holds one of several kinds (``[]``: each item of a list)."""
    fields = {}
    for name, hint in typing.get_type_hints(schema).items():
        where = path + name
        if typing.get_origin(hint) is list:
            hint, where = typing.get_args(hint)[0], where + "[]"
        options = ([a for a in typing.get_args(hint) if a is not type(None)]
                   if typing.get_origin(hint) is Union else [hint])
        kinds = [option for option in options if dataclasses.is_dataclass(option)]
        if len(kinds) > 1:
            fields[where] = ["!" + kind.__name__ for kind in kinds]
        for kind in kinds:
            fields.update(variant_fields(kind, where + "."))
    return fields


def test_the_documented_tags_are_the_schemas():
    documented = {field: [tag.strip().strip("`") for tag in tags.split(",")]
                  for field, tags in table_rows("scenario tags")}
    assert documented == variant_fields(Scenario)

