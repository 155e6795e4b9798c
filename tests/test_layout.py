"""The folders' import rule: analysis -> diagrams -> systems -> hardware (and the
model files of plant_models); only the CLI reaches everywhere."""

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
CLI = REPO / "diagrams" / "cli.py"


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
             for path in sorted((REPO / folder).rglob("*.py")) if path != CLI
             for line, target in project_imports(path)
             if target != folder and target not in ALLOWED[folder]]
    assert not wrong, "\n".join(wrong)
