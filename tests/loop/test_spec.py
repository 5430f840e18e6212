"""The one job-spec contract (service/loop/spec.py): defaults, the λ range, the stored form and
scene parameters, as every way in (loop, API schema, CLI) sees them. No rendering."""
from __future__ import annotations

import dataclasses

import pytest

from service.api.schemas import JobCreate, LambdaUpdate
from service.cli import build_parser, main, render_spec
from service.loop.spec import LAMBDA_RANGE, LoopSpec, LoopSpecError, lambda_problem, validate_spec

OUT_OF_RANGE = 11.0
MESSAGE = lambda_problem(OUT_OF_RANGE)


def test_the_lambda_range_message_names_the_one_range():
    assert MESSAGE == f"λ must be finite and lie in [{LAMBDA_RANGE[0]:g}, {LAMBDA_RANGE[1]:g}]"
    assert lambda_problem(LAMBDA_RANGE[0]) is None and lambda_problem(LAMBDA_RANGE[1]) is None


def test_lambda_outside_the_one_range_reads_the_same_in_loop_api_and_cli(tmp_path, capsys):
    with pytest.raises(LoopSpecError, match=MESSAGE.replace("[", r"\[").replace("]", r"\]")):
        validate_spec(LoopSpec(scene="cornell-box", lam=OUT_OF_RANGE))
    for model, body in [(JobCreate, {"scene": "cornell-box", "lambda": OUT_OF_RANGE}),
                        (LambdaUpdate, {"value": OUT_OF_RANGE}),
                        (LambdaUpdate, {"rects": [{"x": 0, "y": 0, "w": 1, "h": 1, "value": OUT_OF_RANGE}]})]:
        with pytest.raises(ValueError) as caught:
            model.model_validate(body)
        assert MESSAGE in str(caught.value), model.__name__
    for argv in (["render", "cornell-box", "--lambda", str(OUT_OF_RANGE), "-o", str(tmp_path / "o.exr")],
                 ["denoise", str(tmp_path / "in.exr"), "--lambda", str(OUT_OF_RANGE), "-o", str(tmp_path / "o.exr")]):
        assert main(argv) == 2
        assert MESSAGE in capsys.readouterr().err, argv[0]


def test_cli_defaults_are_the_spec_defaults():
    args = build_parser().parse_args(["render", "cornell-box", "-o", "out.exr"])
    assert render_spec(args) == LoopSpec(scene="cornell-box")


def test_cli_param_maps_to_scene_parameters():
    args = build_parser().parse_args(["render", "s.xml", "--param", "albedo=0.5", "--param", "n=3", "-o", "o.exr"])
    assert render_spec(args).params == {"albedo": "0.5", "n": "3"}


@pytest.mark.parametrize("params, message", [({"not an id": "1"}, "identifier"), ({"x": "v" * 5000}, "characters"),
                                             ({"x": 3}, "string")])
def test_bad_scene_parameters_are_refused(params, message):
    with pytest.raises(LoopSpecError, match=message):
        validate_spec(LoopSpec(scene="cornell-box", params=params))


def test_a_budget_below_the_first_iteration_is_refused_not_overspent():
    with pytest.raises(LoopSpecError, match="below spp_first"):
        validate_spec(LoopSpec(scene="cornell-box", spp_first=16, spp_budget=8.0))
    validate_spec(LoopSpec(scene="cornell-box", spp_first=16, spp_budget=16.0))  # exactly the first pass: fine


def test_the_stored_spec_parses_back_into_the_same_loop_spec():
    spec = LoopSpec(scene="cornell-box", width=32, height=24, frames=2, max_iterations=None, spp_budget=64.0,
                    allocator="variance", lam=2.5, seed=7, params={"a": "1"})
    stored = spec.to_stored()
    assert stored["lambda"] == 2.5 and "lam" not in stored
    assert LoopSpec.from_stored(stored) == spec
    assert LoopSpec.from_stored(stored, scene="/jobs/x/bundle/s.xml") == dataclasses.replace(
        spec, scene="/jobs/x/bundle/s.xml")
    with pytest.raises(LoopSpecError, match="unknown job spec field"):
        LoopSpec.from_stored({**stored, "colour": "red"})


def test_api_schema_fields_are_the_spec_fields():
    # budget_source is set by the server (the scene's sample_count), never asked for
    spec_fields = {f.name for f in dataclasses.fields(LoopSpec)} - {"scene", "budget_source"}
    assert spec_fields <= set(JobCreate.model_fields)
    assert JobCreate.model_validate({"scene": "cornell-box"}).loop_spec("cornell-box") == LoopSpec(scene="cornell-box")


def test_a_job_over_the_memory_cap_is_refused_with_its_estimate():
    from dataclasses import replace

    from service.loop.spec import SERVICE_LIMITS, check_limits, estimated_memory

    spec = LoopSpec(scene="cornell-box", frames=16, max_iterations=1, spp_first=1)
    assert estimated_memory(2048, 2048, 16) > SERVICE_LIMITS.max_memory_bytes  # 2048² × 16 frames
    with pytest.raises(LoopSpecError, match="GiB"):
        check_limits(spec, 2048, 2048)
    roomy = replace(SERVICE_LIMITS, max_memory_bytes=256 * 2**30)
    check_limits(spec, 2048, 2048, roomy)  # the same job fits a server configured for it
