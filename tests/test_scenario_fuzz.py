"""Fuzzed scenarios (hypothesis): any one field of any shipped scenario set to a
malformed value, or an unknown field added, is either a scenario that loads or is
refused with one line that names the field; never another error, and on the command
line exit code 2 without a traceback."""

import json
import math

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydrake.common.yaml import yaml_load_data

from maglev_haptics.cli import main
from maglev_haptics.diagrams.scenario import (
    ScenarioError, load_scenario, scenario_names, shipped_scenario_files)

SHIPPED = [(path, name) for path in shipped_scenario_files() for name in scenario_names(path)]
MALFORMED = [-1, 0, -1e300, 1e300, math.nan, math.inf, -math.inf, "text", "", True, None,
             [], [1.0, 2.0], [[1.0]], {}, {"x": 1.0}, 7]


def raw_scenario(path, name) -> dict:
    """The scenario ``name`` as Drake's YAML loader reads it (tags as ``_tag`` keys)."""
    return yaml_load_data(path.read_text())[name] or {}


def field_paths(node, keys=()):
    """Every key path in ``node``, to mappings, lists and values alike."""
    items = (node.items() if isinstance(node, dict)
             else enumerate(node) if isinstance(node, list) else ())
    for key, value in items:
        if key != "_tag":
            yield keys + (key,)
            yield from field_paths(value, keys + (key,))


def to_yaml(node) -> str:
    """Flow-style YAML of ``node``; a ``_tag`` key becomes the mapping's tag."""
    if isinstance(node, dict):
        body = ", ".join(f"{key}: {to_yaml(value)}" for key, value in node.items()
                         if key != "_tag")
        return f"{node['_tag']} {{{body}}}" if "_tag" in node else f"{{{body}}}"
    if isinstance(node, list):
        return "[" + ", ".join(to_yaml(value) for value in node) + "]"
    if isinstance(node, bool) or node is None:
        return json.dumps(node)
    if isinstance(node, float):
        return ".nan" if math.isnan(node) else (".inf" if node > 0 else "-.inf") \
            if math.isinf(node) else repr(node)
    return json.dumps(node)


def with_field(node, keys, value, whole: bool = False):
    """The ``--scenario-text`` node that sets the field at ``keys`` under ``node`` to
    ``value``: mappings keep their tags (a field of several kinds needs one), and
    a list is given whole, as a layer replaces it."""
    if not keys:
        return value
    key, rest = keys[0], keys[1:]
    if isinstance(node, list):
        return [with_field(item, rest, value, whole=True) if i == key else item
                for i, item in enumerate(node)]
    layer = dict(node) if whole else {"_tag": node["_tag"]} if "_tag" in node else {}
    layer[key] = with_field(node.get(key), rest, value, whole)
    return layer


def _at(node, keys):
    for key in keys:
        node = node[key]
    return node


@st.composite
def malformed_scenarios(draw):
    """(path, name, scenario_text, the field name the refusal must say)."""
    path, name = draw(st.sampled_from(SHIPPED))
    raw = raw_scenario(path, name)
    keys = draw(st.sampled_from(list(field_paths(raw)) or [()]))
    if not keys or draw(st.booleans()) and isinstance(_at(raw, keys), dict):
        keys = keys + ("no_such_field",)  # an unknown field in a mapping
        value = 1.0
    else:
        value = draw(st.sampled_from(MALFORMED))
    named = [key for key in keys if isinstance(key, str)][-1]
    return path, name, to_yaml(with_field(raw, keys, value)), named


@pytest.mark.slow  # 300 scenarios loaded
@settings(max_examples=300, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(malformed_scenarios())
def test_a_malformed_field_loads_or_is_refused_naming_it(case):
    path, name, text, field = case
    try:
        load_scenario(str(path), name, scenario_text=text)
    except ScenarioError as error:
        message = str(error)
        assert "\n" not in message, message
        assert field in message, f"{text} -> {message}"


@pytest.mark.parametrize("text, field", [
    ("{controller: {lost_grace_s: .nan}}", "lost_grace_s"),
    ("{motion: {waypoints: [{pose: [0, 0, 0.02]}]}}", "pose"),
    ("{watchdog: {max_speed_m_s: text}}", "max_speed_m_s"),
    ("{device: {amplifier: {current_limit_a: -1}}}", "current_limit_a"),
])
def test_on_the_command_line_it_is_exit_code_2_and_one_line(text, field, capsys):
    try:
        code = main(["run", "levitate", "--no-meshcat", "--scenario-text", text])
    except SystemExit as exit_:
        code = exit_.code
    err = capsys.readouterr().err
    assert code == 2
    assert field in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1, err


def test_in_a_file_too_the_refusal_names_the_field_and_its_type(tmp_path):
    scenario_file = tmp_path / "mine.yaml"
    scenario_file.write_text("mine: {motion: {start_xy_yaw: -1}}\n")
    with pytest.raises(ScenarioError, match=r"^mine:mine: motion.start_xy_yaw = -1: must be "
                                            r"a list of numbers$"):
        load_scenario(str(scenario_file))
