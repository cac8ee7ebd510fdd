"""Status lines: each step shows while it runs, then its time; a failed step ends its line; quiet is silent."""

import pytest

from chic_design.progress import Steps, status


def test_a_step_shows_while_it_runs_then_its_time(capsys):
    steps = Steps(show=True, total=2)
    with steps.step("CAD model"):
        assert capsys.readouterr().err == "chic-design: [1/2] CAD model ..."  # shown before the work is done
    err = capsys.readouterr().err
    assert err.startswith(" ") and err.endswith(" s\n") and float(err.split()[0]) >= 0
    with pytest.raises(ValueError), steps.step("export"):
        raise ValueError("boom")
    assert capsys.readouterr().err == "chic-design: [2/2] export ... failed\n"  # the error line starts afresh
    assert set(steps.timings) == {"CAD model"}


def test_quiet_steps_print_nothing_and_still_time(capsys):
    quiet = Steps(show=False, total=2)
    with quiet.step("CAD model"):
        pass
    assert capsys.readouterr().err == ""
    assert set(quiet.timings) == {"CAD model"}


def test_status_is_one_line_on_stderr(capsys):
    status("checking neuro")
    out, err = capsys.readouterr()
    assert out == "" and err == "chic-design: checking neuro\n"
