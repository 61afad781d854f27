"""Every cookbook example a test here calls returns what ``liecontrol cookbook run`` accepts (named boolean
checks, numeric values): its ``run`` is wrapped by the command's own contract check."""

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
