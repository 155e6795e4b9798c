"""The folders' import rule: analysis -> diagrams -> systems -> hardware (and the
model files of plant_models); the package's root holds the command line (cli.py), above
them all, which no folder imports."""

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# What each folder may import from the project, besides itself.
ALLOWED = {
    "hardware": set(),
    "plant_models": set(),
    "systems": {"hardware", "plant_models"},
    "diagrams": {"systems", "hardware", "plant_models"},
    "analysis": {"diagrams", "systems", "hardware", "plant_models"},
}


def project_imports(path: Path):
    """(line, folder) of each maglev_haptics.<folder> import in the module, nested ones too."""
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names = ([node.module] if isinstance(node, ast.ImportFrom) and node.module
                 else [alias.name for alias in node.names] if isinstance(node, ast.Import)
                 else [])
        for name in names:
            parts = name.split(".")
            if parts[0] == "maglev_haptics" and len(parts) > 1:
                yield node.lineno, parts[1]


@pytest.mark.parametrize("folder", sorted(ALLOWED))
def test_imports_flow_one_way(folder):
    wrong = [f"{path.relative_to(REPO)}:{line} imports {target}"
             for path in sorted((REPO / folder).rglob("*.py"))
             for line, target in project_imports(path)
             if target != folder and target not in ALLOWED[folder]]
    assert not wrong, "\n".join(wrong)


def test_no_folder_imports_the_command_line():
    """The root's modules stand above every folder: an import of them from a folder
    would run back up."""
    roots = {path.stem for path in REPO.glob("*.py") if path.stem != "__init__"}
    wrong = [f"{path.relative_to(REPO)}:{line} imports {target}"
             for folder in ALLOWED for path in sorted((REPO / folder).rglob("*.py"))
             for line, target in project_imports(path) if target in roots]
    assert roots == {"cli"} and not wrong, (roots, wrong)
