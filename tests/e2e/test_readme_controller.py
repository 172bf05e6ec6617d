"""The README's "Test your own controller" example runs as written: its two files are
taken from the README, put in an empty folder outside the repository and run with pytest
(the installed plugin provides the ``swarm`` fixture)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

README = Path(__file__).resolve().parents[2] / "README.md"


def readme_example() -> tuple[str, str]:
    """(my_controller.py, test_my_controller.py) as the README shows them."""
    text = README.read_text()
    section = text[text.index("## Test your own controller"):]
    section = section[:section.index("\n## ", 1)]
    code = re.search(r"```python\n(.*?)```", section, re.S)
    assert code is not None, "the section has no python example"
    controller, test = code.group(1).split("# test_my_controller.py\n")
    return controller.split("\n", 1)[1], test


def test_the_readme_controller_example_passes(tmp_path: Path) -> None:
    controller, test = readme_example()
    assert "make_controller" in controller and "def test_" in test
    (tmp_path / "my_controller.py").write_text(controller)
    (tmp_path / "test_my_controller.py").write_text(test)
    res = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "test_my_controller.py"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-2000:]
    assert re.search(r"\b1 passed\b", res.stdout), res.stdout[-2000:]
