"""One installed name: the repository's folders ``protocol/``, ``world/``, ``agents/`` and
``server/`` are importable only as ``tagswarm.protocol`` ... (through the relative
symlinks in ``tagswarm/``), a wheel holds nothing at its top level but ``tagswarm``, and no
file imports the bare names (importing a module under two names would load it twice, with
two different msgspec classes)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PROCESS_PACKAGES = ("protocol", "world", "agents", "server")
_NAMES = "|".join(PROCESS_PACKAGES)
#: ``import world``, ``from server.x import``, also inside strings (scripts built by tests)
#: and module names handed to ``python -m``, ``import_module`` or ``resources.files``
BARE = re.compile(
    rf"""(?:^|["'])\s*(?:import\s+(?:{_NAMES})\b|from\s+(?:{_NAMES})[.\s])"""
    rf"""|["']-m["'],\s*["'](?:{_NAMES})\.|import_module\(\s*["'](?:{_NAMES})\b|files\(\s*["'](?:{_NAMES})\b""",
    re.M)


def _python_files() -> list[Path]:
    out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard", "*.py"],
                         cwd=ROOT, capture_output=True, text=True, check=True).stdout
    return [ROOT / f for f in out.split("\0") if f and not (ROOT / f).is_symlink() and (ROOT / f).is_file()]


def test_no_file_imports_the_bare_package_names() -> None:
    files = [p for p in _python_files() if p != Path(__file__).resolve()]  # this file holds examples
    assert len(files) > 150 and ROOT / "server" / "fusion.py" in files
    offenders = [f"{p.relative_to(ROOT)}:{p.read_text()[:m.start()].count(chr(10)) + 1}: {m.group(0).strip()}"
                 for p in files for m in BARE.finditer(p.read_text())]
    assert offenders == [], "import these as tagswarm.<package>:\n" + "\n".join(offenders)


@pytest.mark.parametrize("text", ["import server\n", "from world.sim import Sim\n", "    from protocol import codec\n",
                                  '"from agents.detect import X\\n"', '[sys.executable, "-m", "world.node"]',
                                  'resources.files("protocol")', 'importlib.import_module("server.node")'])
def test_the_scan_finds_bare_imports(text: str) -> None:
    assert BARE.search(text)


@pytest.mark.parametrize("text", ["from tagswarm.server import node\n", "import tagswarm.world\n",
                                  'journal = out / "server.journal"', "world.put(key, b'x')\n"])
def test_the_scan_leaves_qualified_names_alone(text: str) -> None:
    assert not BARE.search(text)


def test_each_process_package_is_a_relative_symlink_in_tagswarm() -> None:
    for name in PROCESS_PACKAGES:
        link = ROOT / "tagswarm" / name
        assert link.is_symlink() and os.readlink(link) == f"../{name}"
        assert (ROOT / name).is_dir() and not (ROOT / name).is_symlink()


def _dockerfile_copies() -> list[str]:
    """The sources of the Dockerfile's ``COPY SRC... DEST`` lines (the build context's paths)."""
    srcs: list[str] = []
    for line in (ROOT / "Dockerfile").read_text().splitlines():
        words = line.split()
        if words[:1] == ["COPY"]:
            srcs += words[1:-1]
    return srcs


def test_wheel_built_from_the_docker_context_holds_only_tagswarm(tmp_path: Path) -> None:
    """Copy what the Dockerfile copies (symlinks stay symlinks, as ``COPY`` keeps them), build the
    wheel as ``pip install .`` does, then install it away from the repository and import it."""
    context = tmp_path / "context"
    context.mkdir()
    for src in _dockerfile_copies():
        if (ROOT / src).is_dir():
            shutil.copytree(ROOT / src, context / src, symlinks=True,
                            ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
        else:
            shutil.copy2(ROOT / src, context / src)
    assert (context / "tagswarm" / "server").is_symlink() and (context / "tagswarm" / "server" / "fusion.py").is_file()
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(wheels), str(context)],
                   check=True, capture_output=True, timeout=240)
    (wheel,) = wheels.glob("tagswarm-*.whl")
    with zipfile.ZipFile(wheel) as z:
        infos = {i.filename: i for i in z.infolist()}
    tops = {name.split("/")[0] for name in infos}
    assert tops == {"tagswarm", wheel.name.split("-py3")[0] + ".dist-info"}
    for name in PROCESS_PACKAGES:  # real files, not links: a zip entry of a symlink has the S_IFLNK mode bit
        init = infos[f"tagswarm/{name}/__init__.py"]
        assert (init.external_attr >> 16) & 0o170000 != 0o120000
    assert infos["tagswarm/server/fusion.py"].file_size == (ROOT / "server" / "fusion.py").stat().st_size
    assert "tagswarm/protocol/scenarios/paper.toml" in infos
    assert any(n.startswith("tagswarm/") and n.endswith("/web/index.html") for n in infos)
    entry_points = zipfile.ZipFile(wheel).read(wheel.name.split("-py3")[0] + ".dist-info/entry_points.txt").decode()
    assert "tagswarm-server = tagswarm.server.node:main" in entry_points

    site = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-index", "--target", str(site),
                    str(wheel)], check=True, capture_output=True, timeout=120)
    assert sorted(p.name for p in site.iterdir() if not p.name.endswith(".dist-info") and p.name != "bin") \
        == ["tagswarm"]
    probe = ("import importlib.util, tagswarm, tagswarm.protocol.scenario as s;"
             "print(tagswarm.__file__); print(s.load_scenario('paper').name);"
             "print([n for n in ('protocol', 'world', 'agents', 'server') if importlib.util.find_spec(n)])")
    out = subprocess.run([sys.executable, "-c", probe], cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(site)},
                         capture_output=True, text=True, check=True, timeout=60).stdout.splitlines()
    assert out == [str(site / "tagswarm" / "__init__.py"), "paper", "[]"]
