"""chic-design optimize: requirements validation, design space, Pareto logic, search determinism and resumption."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from chic_design.cli.main import main
from chic_design.errors import SpecError
from chic_design.families import FAMILIES
from chic_design.optimize import space
from chic_design.optimize.choose import knee_order, weakly_dominating
from chic_design.optimize.engine import SerialEngine, make_engine, parse_scheduler
from chic_design.optimize.errors import RequirementsError
from chic_design.optimize.report import write_spec
from chic_design.optimize.requirements import load_requirements
from chic_design.optimize.score import dominates, pareto_front
from chic_design.optimize.search import run_search
from chic_design.optimize.store import ResultStore
from chic_design.spec import load_spec, parse_spec
from tests.conftest import ROOT

CHIC = FAMILIES["chic"]
SMALL = ROOT / "tests" / "data" / "optimize-small.yaml"
NEURO_REQ = ROOT / "designs" / "requirements" / "neuro.yaml"
#: a feasible start for the small requirements (the needle-guide layout on a 28 mm body)
SMALL_START = {"od_halfmm": 32, "length_mm": 28, "channel_tenthmm": 16, "circle_pos": 10, "offset_deg": 15,
               "direction": 1, "free_quadrant": 3, "n_orientation": 2, "orient_a_deg": 24, "orient_b_deg": 60}


def _data(path=SMALL) -> dict:
    return yaml.safe_load(Path(path).read_text(encoding="utf-8"))


# ----------------------------------------------------------------------------- requirements


@pytest.mark.parametrize("edit, fragment", [
    (lambda d: d.update(colour="red"), "unknown key 'colour'"),
    (lambda d: d["limits"].pop("max_length"), "missing key 'limits.max_length'"),
    (lambda d: d["tool"].update(outer_diameter=6), "tool: give either bore_diameter or outer_diameter"),
    (lambda d: d["imaging"].update(pixel_size=-1), "imaging.pixel_size"),
    (lambda d: d["required"].update(depth_mm=[20, 10]), "required: depth_mm must be [low, high]"),
    (lambda d: d["required"].update(depth_mm=[5, 40]), "beyond limits.max_length"),
    (lambda d: d["limits"].update(max_outer_diameter=12), "limits.max_outer_diameter (12)"),
    (lambda d: d["printer"].update(max_channel_diameter=1.0), "max_channel_diameter (1) must be >="),
])
def test_bad_requirements_give_one_line_naming_file_and_key(tmp_path, edit, fragment):
    d = _data()
    edit(d)
    p = tmp_path / "req.yaml"
    p.write_text(yaml.safe_dump(d))
    with pytest.raises(RequirementsError) as e:
        load_requirements(p)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(str(p)) and fragment in msg, msg


def test_cli_bad_requirements_exit_2_without_traceback(tmp_path, capsys):
    p = tmp_path / "req.yaml"
    p.write_text("name: x\ntool: [1, 2\n")
    assert main(["optimize", str(p), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "not valid YAML" in err and str(p) in err
    assert main(["optimize", str(tmp_path / "missing.yaml")]) == 2
    assert main(["optimize", str(SMALL), "--scheduler", "udp://x"]) == 2
    assert "tcp://HOST:PORT or local:N" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_example_requirements_load_and_neuro_baseline_is_in_the_space():
    req = load_requirements(NEURO_REQ)
    needle = load_requirements(ROOT / "designs" / "requirements" / "needle-guide.yaml")
    assert needle.limits.max_outer_diameter <= 12 and needle.imaging.pixel_size == 0.3
    assert needle.imaging.slice_thickness == 1.5
    spec = load_spec(ROOT / "designs" / "neuro.yaml")
    params = space.params_from_spec(spec, req)
    assert params is not None
    # the parameters rebuild exactly the hand-made design: same tube centrelines
    again = parse_spec(space.spec_dict(params, req, "neuro"))
    assert CHIC.geometry(again).tubes == CHIC.geometry(spec).tubes


# ----------------------------------------------------------------------------- Pareto logic


def _r(od, region, tre, feasible=True):
    return {"feasible": feasible, "objectives": {"outer_diameter_mm": od, "usable_region_deg_mm": region,
                                                 "tre_mm": tre}}


def test_pareto_front_hand_worked():
    a, b, c, d = _r(10, 100, 0.2), _r(12, 150, 0.2), _r(12, 100, 0.3), _r(8, 50, 0.5)
    infeasible_best = _r(1, 1000, 0.01, feasible=False)
    assert dominates(a["objectives"], c["objectives"]) and not dominates(a["objectives"], b["objectives"])
    front = pareto_front([a, b, c, d, infeasible_best, dict(a)])
    assert front == [a, b, d]  # c dominated by a; the infeasible one never; duplicate of a once
    assert weakly_dominating(front, c) == [a, b]
    order = knee_order(front)
    assert sorted(order) == [0, 1, 2] and order[-1] == 2  # d is worst on two objectives


# ----------------------------------------------------------------------------- search


@pytest.fixture(scope="module")
def serial_run(tmp_path_factory):
    req = load_requirements(SMALL)
    path = tmp_path_factory.mktemp("store") / "c.sqlite"
    with ResultStore(path) as store:
        res = run_search(req, SerialEngine(), store, trials=8, seed=3, population=4,
                         start_params=SMALL_START, progress=False)
    return req, path, res


def test_search_visits_feasible_designs_only_into_the_front(serial_run):
    req, _, res = serial_run
    assert res.evaluated == len({c["key"] for c in res.candidates}) and res.cached == 0
    assert res.pareto and all(p["feasible"] for p in res.pareto)
    assert any(not c["feasible"] for c in res.candidates)  # the space does hold infeasible designs
    for c in res.candidates:
        if not c["feasible"]:
            assert c["reasons"] and c["objectives"] is None


def test_resume_skips_finished_candidates(serial_run, tmp_path):
    req, path, first = serial_run
    copy = tmp_path / "c.sqlite"
    copy.write_bytes(path.read_bytes())
    with ResultStore(copy) as store:
        # a stored result is used as it is: mark one to prove it is not recomputed
        k = first.candidates[1]["key"]
        marked = {**store.get_many([k])[k], "cpu_s": -123.0}
        store.put(k, first.candidates[1]["params"], marked)
        more = run_search(req, SerialEngine(), store, trials=12, seed=3, population=4,
                          start_params=SMALL_START, progress=False)
        assert len(store) == len({c["key"] for c in more.candidates})
    assert more.cached == 8 and more.evaluated == len({c["key"] for c in more.candidates[8:]} -
                                                      {c["key"] for c in more.candidates[:8]})
    assert [c["key"] for c in more.candidates[:8]] == [c["key"] for c in first.candidates]
    assert more.candidates[1]["cpu_s"] == -123.0


@pytest.mark.slow  # a LocalCluster's start-up dominates (10-30 s under load)
def test_dask_local_cluster_gives_the_same_pareto_set(serial_run):
    pytest.importorskip("distributed")
    req, _, ref = serial_run
    engine = make_engine(parse_scheduler("local:2"))
    try:
        assert engine.workers == 2
        with ResultStore(None) as store:
            res = run_search(req, engine, store, trials=8, seed=3, population=4, start_params=SMALL_START,
                             progress=False)
    finally:
        engine.close()
    assert res.evaluated == ref.evaluated and res.engine == "dask"
    assert [c["key"] for c in res.candidates] == [c["key"] for c in ref.candidates]
    assert [(p["key"], p["objectives"]) for p in res.pareto] == [(p["key"], p["objectives"]) for p in ref.pareto]


def test_write_spec_refuses_an_invalid_spec(tmp_path):
    req = load_requirements(SMALL)
    good = space.spec_dict(SMALL_START, req, "ok")
    write_spec(good, tmp_path / "ok.yaml")
    assert load_spec(tmp_path / "ok.yaml").body.outer_diameter == 16.0
    bad = {**good, "channels": {"diameter": 5.0, "circle_diameter": 12.0}}  # does not fit in the wall
    with pytest.raises(SpecError):
        write_spec(bad, tmp_path / "bad.yaml")
    assert not (tmp_path / "bad.yaml").exists()


def test_impossible_requirements_write_no_design(tmp_path, capsys):
    d = _data()
    d["required"]["tilt_deg"] = [0, 75]  # no CHIC body of this size registers at 75 deg
    d["search"].pop("baseline")
    p = tmp_path / "req.yaml"
    p.write_text(yaml.safe_dump(d))
    out = tmp_path / "o"
    assert main(["optimize", str(p), "--out", str(out), "--trials", "4", "--workers", "1", "--quiet"]) == 4
    err = capsys.readouterr().err.strip()
    assert "none of 4 candidates meets every requirement" in err and "\n" not in err
    assert (out / "candidates.sqlite").is_file()
    assert not (out / "specs").exists() and not (out / "report.md").exists()


def test_the_progress_bar_counts_each_candidate_once_even_when_asked_twice(monkeypatch):
    """A generation can ask the same design twice: the bar ends at the number of candidates, not above it."""
    import chic_design.optimize.search as search_mod

    counted = []

    class Bar:
        def __init__(self, total, **kwargs):
            self.total, self.n = total, 0

        def update(self, k):
            self.n += k

        def close(self):
            counted.append((self.n, self.total))

    def cheap(params, req_data):
        return {"feasible": False, "reasons": ["cheap"], "constraints": [1.0, 0.0, 0.0, 0.0, 0.0],
                "objectives": None, "precision": None, "spec": {}, "cpu_s": 0.0}

    monkeypatch.setattr(search_mod, "tqdm", Bar)
    monkeypatch.setattr(search_mod, "evaluate_candidate", cheap)
    # two keys only: every generation asks the same designs several times
    monkeypatch.setattr(search_mod.space, "candidate_key", lambda p, req, v: str(p["direction"]))
    req = load_requirements(SMALL)
    with ResultStore(None) as store:
        res = run_search(req, SerialEngine(), store, trials=10, seed=1, population=5, progress=True)
        again = run_search(req, SerialEngine(), store, trials=10, seed=1, population=5, progress=True)
    assert len(res.candidates) == 10 and res.evaluated <= 2 and again.cached == 10
    assert counted == [(10, 10), (10, 10)]
