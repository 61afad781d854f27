"""Packaging metadata a user relies on: the version, the licence and the type-annotation markers."""

from __future__ import annotations

from pathlib import Path

import pytest

import liecontrol
from liecontrol import cli

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("torchlie", "controllers", "learning", "liecontrol")


def _pyproject() -> dict:
    tomllib = pytest.importorskip("tomllib", reason="reading pyproject.toml needs Python >= 3.11's tomllib")
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_version_is_the_package_metadata():
    assert liecontrol.__version__ == _pyproject()["project"]["version"]


def test_cli_version_prints_it_and_exits_0(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == liecontrol.__version__


def test_license_is_an_spdx_expression_with_its_file():
    project = _pyproject()["project"]
    assert project["license"] == "MIT"
    for name in project["license-files"]:
        assert "MIT License" in (ROOT / name).read_text()


@pytest.mark.parametrize("package", PACKAGES)
def test_every_package_is_typed_and_ships_the_marker(package):
    assert (ROOT / package / "py.typed").is_file()
    assert "py.typed" in _pyproject()["tool"]["setuptools"]["package-data"]["*"]
