"""The scene-check child process (service/render/scene_probe.py) on its own: it answers in JSON,
reports a child that dies, and carries none of the service's secrets in its environment."""
from __future__ import annotations

import pytest

from service.render.scene_probe import ProbeFailed, ProbeLimitExceeded, ProbeLimits, SceneProber, child_environment


@pytest.fixture(scope="module")
def prober():
    probe = SceneProber(ProbeLimits(seconds=120), preload="json")
    probe.start()
    yield probe
    probe.close()


def test_a_check_runs_in_a_child_and_its_answer_comes_back(prober, tmp_path):
    assert prober.run(dict, {"scene": "a.xml", "sizes": [1, 2]}, [tmp_path]) == {"scene": "a.xml", "sizes": [1, 2]}


def test_a_check_that_raises_is_a_probe_failure(prober, tmp_path):
    with pytest.raises(ProbeFailed, match="JSONDecodeError|TypeError"):
        prober.run(__import__("json").loads, {"not": "a string"}, [tmp_path])


def test_a_child_that_exits_without_answering_is_reported(prober, tmp_path):
    with pytest.raises(ProbeLimitExceeded, match="ended abnormally"):
        prober.run(__import__("sys").exit, {}, [tmp_path])


def test_the_child_environment_holds_no_service_secrets(monkeypatch):
    monkeypatch.setenv("RENDERLOOP_TOKEN", "secret")
    monkeypatch.setenv("RENDERLOOP_DB", "postgresql://user:pw@db/renderloop")
    monkeypatch.setenv("RAY_AUTH_TOKEN", "ray-secret")
    environment = child_environment()
    assert not {"RENDERLOOP_TOKEN", "RENDERLOOP_DB", "RAY_AUTH_TOKEN"} & set(environment)
    assert "PATH" in environment


def test_a_standby_child_that_died_while_idle_is_replaced(prober, tmp_path):
    prober.start()
    standby = prober._standby
    standby.process.kill()
    standby.process.wait()
    assert prober.run(dict, {"after": "a dead standby"}, [tmp_path]) == {"after": "a dead standby"}
