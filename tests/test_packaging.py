"""What a user gets besides the code: the module entry point, type information, the licence, the changelog."""

from __future__ import annotations

import subprocess
import sys

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]
from pathlib import Path

from tactdeform_hw.cli import build_parser
from tactdeform_hw.cli.options import EarlierSpelling

ROOT = Path(__file__).resolve().parent.parent


def test_python_dash_m_runs_the_command_line() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "tactdeform_hw", "--version"], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("tactdeform-hw ")


def test_the_package_says_it_is_typed_and_ships_the_marker() -> None:
    assert (ROOT / "tactdeform_hw" / "py.typed").is_file()
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "py.typed" in project["tool"]["setuptools"]["package-data"]["tactdeform_hw"]


def test_every_data_file_of_the_package_is_in_its_package_data() -> None:
    """A file the code reads at run time that is not Python (the teapot's patch tables, the host build's
    shim) reaches an installed wheel only through pyproject's package-data: every such file under the
    package matches one of its globs."""
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    package = ROOT / "tactdeform_hw"
    missing = []
    for path in sorted(package.rglob("*")):
        if not path.is_file() or path.suffix in (".py", ".pyc") or "__pycache__" in path.parts:
            continue
        shipped = any(
            path.is_relative_to(ROOT / name.replace(".", "/"))
            and path.relative_to(ROOT / name.replace(".", "/")).match(glob)
            for name, globs in declared.items()
            for glob in globs
        )
        if not shipped:
            missing.append(str(path.relative_to(ROOT)))
    assert (package / "render" / "data" / "teapot_points.txt").is_file()
    assert missing == [], f"files a wheel would not have: {missing}"


def test_the_licence_file_is_the_licence_pyproject_names() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert project["project"]["license"]["text"] == "MIT"
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")


def _deprecated_spellings() -> set[str]:
    found: set[str] = set()
    for name, sub in build_parser().commands.items():
        for action in sub._actions:
            if isinstance(action, EarlierSpelling):
                found.update(f"{name} {flag}" for flag in action.option_strings)
    return found


def test_every_deprecated_spelling_is_in_the_changelog() -> None:
    """A spelling the command line still takes with a warning is one the changelog announces the removal
    of: a row naming the command and the old spelling."""
    rows = [line for line in (ROOT / "CHANGELOG.md").read_text().splitlines() if line.startswith("| `")]
    missing = []
    for entry in sorted(_deprecated_spellings()):
        command, flag = entry.split(" ", 1)
        if not any(f"`{command}`" in row.split("|")[1] and f"`{flag}" in row.split("|")[2] for row in rows):
            missing.append(entry)
    assert missing == [], f"deprecated spellings missing from CHANGELOG.md: {missing}"
