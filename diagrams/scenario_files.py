"""The shipped scenario files and the names in a scenario file, without the schema.

Light on purpose (PyYAML only, no Drake): ``maglev --help`` lists the shipped
scenarios from here, and a help text must not wait for pydrake to import.
"""

from pathlib import Path
from typing import List

import yaml

_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml's where PyYAML has it
# The longest a run, and each script in it, may last (s): a script's setpoints are
# tabled at every control tick (~0.1 kB a tick) and a paced run times every tick.
LONGEST_S = 3600.0
SCENARIO_DIR = Path(__file__).resolve().parent.parent / "scenarios"


class ScenarioError(ValueError):
    """A scenario that cannot be run, with the offending field named."""


def shipped_scenario_files() -> List[Path]:
    return sorted(SCENARIO_DIR.glob("*.yaml"))


def resolve_scenario_file(name_or_path: str) -> Path:
    """A path, or the stem of a shipped scenario file (``levitate``)."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    shipped = SCENARIO_DIR / f"{name_or_path}.yaml"
    if shipped.is_file():
        return shipped
    names = ", ".join(p.stem for p in shipped_scenario_files())
    raise ScenarioError(f"scenario file {name_or_path!r} not found: give a path or one of {names}")


def read_text_file(path: Path, source: str) -> str:
    """The text of the file at ``path``; a ScenarioError naming ``source`` where it is
    not UTF-8 text (an image or another binary file given by mistake)."""
    data = Path(path).read_bytes()
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise ScenarioError(
            f"{source}: not a text file (byte {data[error.start]:#04x} at offset "
            f"{error.start} is not UTF-8): give a YAML file") from None


def yaml_error(source: str, error: yaml.YAMLError) -> ScenarioError:
    """PyYAML's error as one line naming ``source``, the line and the column."""
    mark = getattr(error, "problem_mark", None)
    where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
    problem = getattr(error, "problem", None) or str(error).splitlines()[0]
    return ScenarioError(f"{source}: not valid YAML{where}: {problem}")


def check_unique_keys(text: str, source: str) -> None:
    """Raise a ScenarioError naming ``source``, the key's path and both lines where a
    mapping in the YAML ``text`` gives a key twice: YAML keeps the last one silently,
    so the first would be ignored without a word."""
    try:
        root = yaml.compose(text, Loader=_LOADER)
    except yaml.YAMLError as error:
        raise yaml_error(source, error) from None
    pending = [(root, "")]  # in the file's order, outer keys first
    while pending:
        node, path = pending.pop(0)
        if isinstance(node, yaml.MappingNode):
            first_line = {}
            for key, value in node.value:
                name = key.value if isinstance(key, yaml.ScalarNode) else str(key.value)
                if name in first_line:
                    lines = sorted({first_line[name], key.start_mark.line + 1})
                    where = " and ".join(map(str, lines))
                    raise ScenarioError(
                        f"{source}: {path}{name}: given twice (line{'s' if len(lines) > 1 else ''} "
                        f"{where}); say each key once")
                first_line[name] = key.start_mark.line + 1
                pending.append((value, f"{path}{name}."))
        elif isinstance(node, yaml.SequenceNode):
            pending.extend((item, f"{path.rstrip('.')}[{i}].")
                           for i, item in enumerate(node.value))


def scenario_names(path: Path) -> List[str]:
    """The named scenarios in the file at ``path``, in its order (``Defaults`` left out).
    Reads the YAML's structure only (tags need no schema here)."""
    try:
        node = yaml.compose(read_text_file(path, str(path)), Loader=_LOADER)
    except yaml.YAMLError as error:
        raise yaml_error(str(path), error) from None
    if node is None:
        return []
    if not isinstance(node, yaml.MappingNode):
        raise ScenarioError(f"{path}: must be a YAML mapping of named scenarios")
    return [key.value for key, _ in node.value if key.value != "Defaults"]
