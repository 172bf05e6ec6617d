"""The README's Layout section names every module and package folder of the tree, and
nothing that is not there."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
FOLDERS = ("protocol", "world", "agents", "server", "tagswarm")


def _layout() -> str:
    text = (ROOT / "README.md").read_text()
    return text.split("\n## Layout\n", 1)[1].split("\n## ", 1)[0]


def _tree() -> tuple[set[str], set[str]]:
    """(module file names, package folder names) of the product (links not followed: each once),
    and the test helpers."""
    modules, folders = set(), set()
    for top in FOLDERS:
        for path in (ROOT / top).rglob("*.py"):
            if "__pycache__" not in path.parts and path.name != "__init__.py":
                modules.add(path.name)
                if path.parent != ROOT / top:
                    folders.add(path.parent.name)
    helpers = {p.name for p in (ROOT / "tests").rglob("*.py") if not p.name.startswith("test_")}
    return modules | (helpers - {"__init__.py"}), folders


def test_layout_names_every_module_and_folder() -> None:
    layout = _layout()
    named = set(re.findall(r"`([\w.]+\.py)`", layout))
    modules, folders = _tree()
    assert len(modules) > 70  # file names: node.py, config.py ... count once
    assert sorted(modules - named) == [], "modules missing from the README's Layout section"
    assert sorted(named - modules) == [], "the README's Layout names modules that do not exist"
    for folder in folders | set(FOLDERS):
        assert f"`{folder}/`" in layout or f"`tagswarm/{folder}/`" in layout, folder
