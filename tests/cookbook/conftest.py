"""Shared by the cookbook example tests: ``run_example(module)`` runs an example into a temporary folder
and checks what every example owes — the outcome contract of ``liecontrol cookbook run`` (named boolean
checks, numeric values), every check true, its figure written — and returns its values.  Calls through a
module's ``run`` attribute are also checked against the contract (autouse)."""

import sys

import pytest

from liecontrol.cookbook import _check_outcome


@pytest.fixture(autouse=True)
def _examples_keep_the_contract(monkeypatch):
    for name, mod in list(sys.modules.items()):
        if name.startswith("examples.cookbook.") and callable(getattr(mod, "run", None)):
            def checked(*args, _run=mod.run, _name=name, **kwargs):
                out = _run(*args, **kwargs)
                _check_outcome(_name, out)
                return out

            monkeypatch.setattr(mod, "run", checked)


@pytest.fixture
def run_example(tmp_path):
    def run(mod) -> dict:
        name = mod.__name__.rsplit(".", 1)[-1]
        res = mod.run(tmp_path)
        checks, values = _check_outcome(name, res)
        failed = [k for k, v in checks.items() if not v]
        assert not failed, (failed, values)
        assert (tmp_path / f"{name}.png").stat().st_size > 1000
        assert isinstance(mod.SECTION, str) and isinstance(mod.TITLE, str)
        return values

    return run
