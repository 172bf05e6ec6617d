"""The tests mirror the package tree: tests/unit/<package>/ for each package that has unit
tests, every test file name unique across the tiers, and each tier marked by its folder."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parents[1]
PACKAGE = TESTS.parent / "tagswarm"


def test_every_test_file_name_is_unique_across_the_tiers() -> None:
    names = Counter(p.name for p in TESTS.rglob("test_*.py"))
    assert len(names) > 60
    assert [n for n, k in names.items() if k > 1] == []


def test_unit_test_folders_are_packages_of_tagswarm() -> None:
    folders = {p.name for p in (TESTS / "unit").iterdir() if p.is_dir() and p.name != "__pycache__"}
    packages = {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").is_file()}
    assert {"protocol", "runtime", "world", "agents", "server"} <= folders <= packages
    for folder in folders:
        assert (TESTS / "unit" / folder / "__init__.py").is_file(), folder


def test_tiers_are_marked_by_folder(request: pytest.FixtureRequest) -> None:
    """Every collected test carries its tier's marker (none for unit tests); run with the other
    tiers collected (e.g. the whole suite) it checks them all."""
    tiers = set()
    for item in request.session.items:
        tier = Path(item.path).resolve().relative_to(TESTS).parts[0]
        marks = {m.name for m in item.iter_markers()} & {"integration", "e2e"}
        assert marks == ({tier} if tier in ("integration", "e2e") else set()), item.nodeid
        tiers.add(tier)
    assert "unit" in tiers


def test_every_e2e_module_on_the_real_time_clock_runs_in_the_serial_pass() -> None:
    """scripts/test.sh runs the e2e modules not in SERIAL_E2E on two workers at once; a real-time
    run there would fall behind the wall clock on a loaded machine, so a new module that asks for
    ``realtime`` must be listed, and every listed module must exist."""
    from tests.conftest import SERIAL_E2E

    modules = {p.stem: p.read_text() for p in (TESTS / "e2e").glob("test_*.py")}
    realtime = {name for name, text in modules.items() if "realtime" in text}
    assert len(realtime) >= 5
    assert sorted(realtime - SERIAL_E2E) == []
    assert sorted(SERIAL_E2E - set(modules)) == []
