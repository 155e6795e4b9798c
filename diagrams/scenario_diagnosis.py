"""A scenario's YAML, read and, where Drake's typed loader refuses it, explained.

``parse_mapping`` reads a file's or an overlay's text as a mapping (a key given twice
is named with its lines). ``load_typed`` runs Drake's ``yaml_load_typed`` and turns
any refusal into one line that names the field, its value and what it must be: an
unknown field or tag is found from the schema's dataclasses before loading; a value
Drake cannot convert, by loading the raw fields one at a time. The schema itself is
``diagrams/scenario.py``.
"""

import dataclasses
import typing
from typing import Union

import yaml
from pydrake.common.yaml import yaml_load_data

from maglev_haptics.diagrams.scenario_files import ScenarioError, check_unique_keys, yaml_error


def parse_mapping(text: str, source: str) -> dict:
    """The YAML mapping in ``text``, as Drake's loader reads it; a ScenarioError
    naming ``source`` if it is not one."""
    check_unique_keys(text, source)
    try:
        raw = yaml_load_data(text)
    except yaml.YAMLError as error:
        raise yaml_error(source, error) from None
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise ScenarioError(f"{source}: must be a YAML mapping, not {type(raw).__name__}")
    return raw


def _field_path(keys) -> str:
    return "".join(f"[{key}]" if isinstance(key, int) else f".{key}" for key in keys).lstrip(".")


def _options(hint) -> list:
    """A Union's members, None left out; [hint] for anything else."""
    if typing.get_origin(hint) is Union:
        return [a for a in typing.get_args(hint) if a is not type(None)]
    return [hint]


def _fields(schema):
    """{field name: type} of a config class (a dataclass, or a Drake config type with
    ``__fields__``), in their order; None for anything else."""
    if dataclasses.is_dataclass(schema):
        return typing.get_type_hints(schema)
    if isinstance(schema, type) and hasattr(schema, "__fields__"):
        return {f.name: f.type for f in schema.__fields__}
    return None


def _hint_at(root, raw, keys):
    """The schema's type hint of the field at ``keys`` (a Union as written), None where
    the path leaves the dataclasses (an unknown field, or inside a Drake config)."""
    hint, node = root, raw
    for key in keys:
        options = _options(hint)
        tag = node.get("_tag", "").lstrip("!") if isinstance(node, dict) else ""
        schema = {option.__name__: option for option in options}.get(tag, options[0])
        if isinstance(key, int):
            if typing.get_origin(schema) is not list:
                return None
            hint = typing.get_args(schema)[0]
        elif _fields(schema) is not None:
            hint = _fields(schema).get(key)
            if hint is None:
                return None
        else:
            return None
        node = node[key]
    return hint


def _check_structure(raw, hint, keys=()) -> None:
    """What Drake's loader would refuse or misread, found from the schema itself: an
    unknown field; a tag that is not one of the field's kinds; an untagged mapping
    where a field holds one of several kinds (Drake would read a hanging ball's
    ``scene: {contact: ...}`` as a fresh PegInHole); a scalar there (Drake would keep
    it as the field's value)."""
    options = _options(hint)
    kinds = [option for option in options if dataclasses.is_dataclass(option)]
    if len(options) > 1:
        nullable = type(None) in typing.get_args(hint)
        if len(kinds) > 1 and raw is not None and not isinstance(raw, dict):
            raise ScenarioError(f"{_field_path(keys)} = {_flow_yaml(raw)}: must be "
                                + _phrase(hint))
        if isinstance(raw, dict):
            named = {option.__name__: option for option in options}
            tag = raw.get("_tag", "").lstrip("!")
            if not tag:
                raise ScenarioError(f"{_field_path(keys)}: needs a tag to choose its kind, one "
                                    f"of {_tags(options)}")
            if tag not in named:
                raise ScenarioError(f"{_field_path(keys)}: !{tag} is not one of "
                                    f"{_tags(options)}" + (", or null" if nullable else ""))
            _check_structure(raw, named[tag], keys)
        return
    schema = options[0]
    if typing.get_origin(schema) is list and isinstance(raw, list):
        for i, item in enumerate(raw):
            _check_structure(item, typing.get_args(schema)[0], keys + (i,))
    elif _fields(schema) is not None and isinstance(raw, dict):
        hints = _fields(schema)
        for key, value in raw.items():
            if key == "_tag":
                continue
            if key not in hints:
                raise ScenarioError(f"{_field_path(keys + (key,))}: unknown field; "
                                    f"{schema.__name__} has " + ", ".join(hints))
            _check_structure(value, hints[key], keys + (key,))


# What Drake's YAML loader raises on data that does not fit the schema (its Python
# half asserts, converts with float(), iterates, and reads a dict field's items).
LOAD_ERRORS = (RuntimeError, ValueError, TypeError, AssertionError, AttributeError)


def _with_only(node, keys):
    """``node`` cut down to the field at ``keys`` (its whole value), the tags of the
    mappings on the way, and a list's one item on the way."""
    if not keys:
        return node
    inner = _with_only(node[keys[0]], keys[1:])
    if isinstance(node, list):
        return [inner]
    cut = {"_tag": node["_tag"]} if "_tag" in node else {}
    cut[keys[0]] = inner
    return cut


def _failing_field(root, raw: dict, load_raw) -> tuple:
    """The deepest key path in ``raw`` whose field alone ``load_raw`` still refuses
    (down through the schema's mappings and lists); () if none does alone."""
    keys, node = (), raw
    while True:
        schema = _options(_hint_at(root, raw, keys))[0] if keys else root
        if isinstance(node, dict) and _fields(schema) is not None or (
                isinstance(node, dict) and len(_options(_hint_at(root, raw, keys))) > 1):
            items = [(key, value) for key, value in node.items() if key != "_tag"]
        elif isinstance(node, list) and typing.get_origin(schema) is list:
            items = list(enumerate(node))
        else:
            return keys
        for key, value in items:
            try:
                load_raw(_with_only(raw, keys + (key,)))
            except LOAD_ERRORS:
                keys, node = keys + (key,), value
                break
        else:
            return keys


def load_typed(root, source: str, raw: dict, load, load_raw):
    """``load()`` (Drake's yaml_load_typed of the schema ``root``, which checks keys,
    types and tags), with
    any refusal as a ScenarioError of one line naming the field, its value and what it
    must be: unknown fields and tags are found from the schema before loading; a value
    Drake cannot convert, by loading ``raw``'s fields alone (``load_raw(cut)``).
    Drake's own message is shown only where no single field is to blame."""
    try:
        _check_structure(raw, root)
        return load()
    except ScenarioError as error:
        raise ScenarioError(f"{source}: {error}") from None
    except LOAD_ERRORS as error:
        keys = _failing_field(root, raw, load_raw)
        if not keys:
            message = (str(error).splitlines() or [type(error).__name__])[0]
            raise ScenarioError(f"{source}: {message}") from None
        value = raw
        for key in keys:
            value = value[key]
        hint = _hint_at(root, raw, keys)
        named = [key for key in keys if isinstance(key, str)][-1]
        what = _phrase(hint, named) if hint is not None else (
            f"what {named} takes ({(str(error).splitlines() or [''])[0]})")
        raise ScenarioError(f"{source}: {_field_path(keys)} = {_flow_yaml(value)}: must be "
                            f"{what}") from None


def _flow_yaml(value) -> str:
    return yaml.safe_dump(value, default_flow_style=True, width=1000).strip().removesuffix(
        "...").strip()


# A field's unit, from its name's suffix (the schema's convention).
UNITS = (("_m_s", "m/s"), ("_rad_s", "rad/s"), ("_n_m", "N*m"), ("_mm", "mm"), ("_hz", "Hz"),
         ("_s", "s"), ("_m", "m"), ("_a", "A"), ("_n", "N"), ("_c", "C"), ("_kg", "kg"),
         ("_rad", "rad"), ("_deg", "deg"), ("_ohm", "ohm"), ("_w", "W"), ("_j", "J"),
         ("_v", "V"), ("_h", "H"))


def _unit(name: str) -> str:
    return next((f" ({unit})" for suffix, unit in UNITS if name.endswith(suffix)), "")


def _tags(options) -> str:
    return ", ".join(f"!{option.__name__} {{...}}" for option in options)


def _phrase(hint, name: str = "") -> str:
    """What a value of the schema type ``hint`` must be, as a user reads it: ``a number
    (s)``, ``a whole number``, ``a list of numbers (m)``, ``one of !A {...}, !B {...}``."""
    options = _options(hint)
    null = ", or null" if type(None) in typing.get_args(hint) else ""
    if len(options) > 1:
        return "one of " + _tags(options) + null
    schema = options[0]
    if schema is float:
        return "a number" + _unit(name) + null
    if schema is int:
        return "a whole number" + null
    if schema is bool:
        return "true or false" + null
    if schema is str:
        return "a string" + null
    if typing.get_origin(schema) is list:
        item = typing.get_args(schema)[0]
        items = {float: "numbers" + _unit(name), int: "whole numbers", str: "strings",
                 bool: "true or false"}.get(item)
        if items is None:
            items = (f"{item.__name__} mappings" if dataclasses.is_dataclass(item)
                     else "mappings, each " + _phrase(item))
        return f"a list of {items}" + null
    if typing.get_origin(schema) is dict:
        return "a mapping" + null
    if _fields(schema) is not None:
        return (f"a mapping of {schema.__name__}'s fields (" + ", ".join(_fields(schema))
                + ")" + null)
    return f"a {getattr(schema, '__name__', str(schema))}" + null
