"""The paper's simulation study: cases, error bookkeeping, summary beside the paper."""


import numpy as np
import pytest

from chic_register.studies.evaluate import PAPER, StudyCase, format_summary, paper_cases, run_study


def test_paper_cases_follow_the_paper(neuro_geometry):
    cases = paper_cases(neuro_geometry)
    assert [c.label for c in cases] == list("EFGHIJKLMABCDNOPQR")
    assert [c.depth_mm for c in cases if c.group == "normal"] == pytest.approx([5, 10, 20, 30, 40])
    assert [c.depth_mm for c in cases if c.group == "tilted"] == pytest.approx([10, 20, 30, 40])
    assert {c.tilt_deg for c in cases if c.group == "tilted"} == {30.0}
    assert [c.tilt_deg for c in cases if c.group == "tilt"] == [15, 30, 45, 60]
    assert [c.twist_deg for c in cases if c.group == "twist"] == [15, 30, 45, 60, 90]


def test_noise_free_study_is_accurate_and_reproducible(neuro_geometry):
    cases = [StudyCase("normal", "G", 20.0, 0.0), StudyCase("tilt", "B", 25.0, 30.0, random_azimuth=True),
             StudyCase("twist", "O", 25.0, 0.0, 30.0)]
    a = run_study(neuro_geometry, draws=2, seed=3, noise="none", cases=cases)
    b = run_study(neuro_geometry, draws=2, seed=3, noise="none", cases=cases)
    assert np.array_equal(a.axial_mm, b.axial_mm)
    assert np.all(np.isfinite(a.axial_mm))
    s = a.summary()
    assert set(s) == {"normal", "tilt", "twist"}
    assert s["normal"]["max"] < 0.02 and s["tilt"]["max"] < 0.1 and s["twist"]["max"] < 0.02
    assert s["normal"]["paper_max"] == PAPER["normal"][0]
    assert s["normal"]["paper_max_over_max"] == pytest.approx(PAPER["normal"][0] / s["normal"]["max"])
    assert "normal sections" in format_summary(a)


@pytest.mark.parametrize("ratio, text", [(3.21, "3.2x better"), (1.0, "1.0x better"), (0.7, "1.4x worse"),
                                         (0.25, "4.0x worse")])
def test_evaluate_says_worse_when_worse(ratio, text):
    from chic_register.studies.evaluate import versus_paper

    assert versus_paper(ratio) == text
