"""`renderloop render` and `renderloop submit` take one set of job options, generated from the
job spec (service/job_options.py over service/loop/spec.py)."""
from __future__ import annotations

import pytest

from service.cli import build_parser
from service.job_options import JOB_FIELDS, SERVICE_ONLY_FIELDS, JobOptionError, api_fields, settable_fields, spec_from_args
from service.loop.spec import DEFAULT_ITERATIONS


def options(command: str) -> dict[str, object]:
    """flag → argparse action of one sub-command."""
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    return {flag: action for action in sub.choices[command]._actions for flag in action.option_strings}


def test_every_job_spec_field_a_user_sets_has_an_option_on_render_and_submit():
    assert set(JOB_FIELDS) == settable_fields()  # a new LoopSpec field needs its flag here
    render, submit = options("render"), options("submit")
    for name, flag in JOB_FIELDS.items():
        assert flag in submit, flag
        assert (flag in render) == (name not in SERVICE_ONLY_FIELDS), flag


def test_render_and_submit_share_names_help_and_defaults():
    render, submit = options("render"), options("submit")
    shared = [flag for flag in render if flag in submit and flag not in ("-h", "--help", "-o", "--output")]
    assert {"--param", "--time-limit", "--spp-budget", "--spp", "--frames", "--allocator", "--no-denoise", "--seed",
            "--lambda", "--target-error", "--iterations", "--png", "--width", "--spp-first"} <= set(shared)
    for flag in shared:
        a, b = render[flag], submit[flag]
        assert (a.help, a.default, a.type, a.dest, a.option_strings) == (b.help, b.default, b.type, b.dest,
                                                                         b.option_strings), flag


def submit_fields(*argv: str) -> dict:
    args = build_parser().parse_args(["submit", "cornell-box", *argv])
    return api_fields(spec_from_args(args, args.scene, default_iterations=None))


def test_submit_sends_what_was_asked_and_leaves_the_default_budget_to_the_server():
    fields = submit_fields("--param", "albedo=0.5", "--time-limit", "30", "--seed", "7", "--no-denoise",
                           "--priority", "5", "--name", "lego turntable", "--lambda", "2")
    assert fields["params"] == {"albedo": "0.5"} and fields["time_limit"] == 30 and fields["seed"] == 7
    assert fields["denoise"] is False and fields["allocator"] == "variance" and fields["lambda"] == 2
    assert fields["priority"] == 5 and fields["name"] == "lego turntable"
    assert "max_iterations" not in fields and "spp_budget" not in fields  # no rule given: the server's default
    assert submit_fields("--spp", "8")["max_iterations"] == 1 and submit_fields("--spp", "8")["spp_first"] == 8
    args = build_parser().parse_args(["render", "cornell-box"])
    assert spec_from_args(args, "cornell-box").max_iterations == DEFAULT_ITERATIONS  # render decides locally


@pytest.mark.parametrize("argv, message", [
    (["--allocator", "magic"], "unknown allocator"),
    (["--priority", "1000"], "priority must be an integer in [-100, 100]"),
    (["--name", "two\nlines"], "name must be one printable line"),
    (["--param", "novalue"], "--param takes NAME=VALUE"),
    (["--spp-budget", "4"], "below spp_first"),
])
def test_a_bad_job_option_is_refused_before_anything_is_sent(argv, message):
    with pytest.raises(JobOptionError, match=message.replace("[", r"\[").replace("]", r"\]")):
        submit_fields(*argv)
