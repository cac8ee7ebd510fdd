"""The package's public API: every name resolves to its one home, and importing the package loads nothing."""

import importlib
import json
import subprocess
import sys

import pytest

import chic_register


@pytest.mark.parametrize("name", sorted(set(chic_register.__all__) - {"__version__"}))
def test_each_public_name_is_its_homes(name):
    home = importlib.import_module(chic_register.API_HOMES[name])
    obj = getattr(chic_register, name)
    assert obj is getattr(home, name)
    assert getattr(obj, "__module__", home.__name__) == home.__name__  # defined there, not re-exported


def test_an_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'regster'"):
        chic_register.regster  # noqa: B018


def test_importing_the_package_loads_no_stage_and_no_numpy():
    code = "import chic_register, json, sys; print(json.dumps(sorted(sys.modules)))"
    mods = json.loads(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, encoding="utf-8", errors="replace",
                                     check=True).stdout)
    assert "numpy" not in mods
    assert [m for m in mods if m.startswith("chic_register.")] == ["chic_register.version"]
