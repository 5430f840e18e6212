"""A missing component fails the test that needs it, naming the component and how to install it;
ALLOW_SKIP=1 turns that into a skip with the same reason (tests/required_components.py). And on a
machine set up by `make test`, every component is there."""
from __future__ import annotations

import pytest

import required_components
from required_components import ALLOW_SKIP, COMPONENTS, Component, import_component, require_component

GONE = Component(lambda: "the test removed it", "bash scripts/ensure-gone.sh")


@pytest.fixture
def gone(monkeypatch) -> str:
    monkeypatch.setitem(COMPONENTS, "gone", GONE)
    monkeypatch.setitem(COMPONENTS, "there", Component(lambda: None, "nothing to do"))
    monkeypatch.delenv(ALLOW_SKIP, raising=False)
    return "gone"


def test_a_missing_component_fails_with_its_name_the_reason_and_the_install_step(gone):
    with pytest.raises(pytest.fail.Exception) as failure:
        require_component(gone)
    assert "gone is missing: the test removed it" in str(failure.value)
    assert "bash scripts/ensure-gone.sh" in str(failure.value) and "ALLOW_SKIP=1" in str(failure.value)


@pytest.mark.parametrize("value", ["", "0", "yes"])
def test_only_allow_skip_1_turns_the_failure_into_a_skip(gone, monkeypatch, value):
    monkeypatch.setenv(ALLOW_SKIP, value)
    with pytest.raises(pytest.fail.Exception):
        require_component(gone)
    monkeypatch.setenv(ALLOW_SKIP, "1")
    with pytest.raises(pytest.skip.Exception, match="gone is missing: the test removed it"):
        require_component(gone)


def test_a_present_component_passes_and_imports(gone, monkeypatch):
    require_component("there")
    monkeypatch.setitem(COMPONENTS, "json", Component(lambda: None, "stdlib"))
    assert import_component("json").dumps([1]) == "[1]"


def test_the_requires_marker_runs_the_check_before_the_test(gone, request):
    conftest = request.config.pluginmanager.get_plugin(f"{request.config.rootpath / 'tests' / 'conftest.py'}")

    class Item:  # the marker as pytest hands it to pytest_runtest_setup
        def iter_markers(self, name):
            return [pytest.mark.requires("there", "gone").mark] if name == "requires" else []

    with pytest.raises(pytest.fail.Exception, match="gone is missing"):
        conftest.pytest_runtest_setup(Item())


def test_the_module_checks_real_components():
    assert set(COMPONENTS) >= {"postgresql", "chromium", "ray", "pyoidn", "landlock"}
    assert required_components._module_missing("no_such_module_anywhere")() is not None
