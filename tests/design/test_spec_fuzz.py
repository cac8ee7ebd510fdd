"""Property-based: mutated specs and spec text give a spec or a one-line SpecError.

Seeded (``derandomize``), modest example counts and a per-example deadline that catches a hang.
"""

from __future__ import annotations

import copy
import tempfile
from pathlib import Path

import yaml
from hypothesis import given
from hypothesis import strategies as st

from chic_design.errors import SpecError
from chic_design.families import family_of
from chic_design.feasibility.printability import build_violations
from chic_design.spec import load_spec, parse_spec
from tests.conftest import NEURO
from tests.helpers import ANY_VALUE, FUZZ, assert_one_line, finite_numbers

NEURO_DATA = yaml.safe_load(NEURO.read_text())


def _paths(data, prefix=()):
    """Every key path of a nested dict (parents and leaves)."""
    for k, v in data.items():
        yield prefix + (k,)
        if isinstance(v, dict):
            yield from _paths(v, prefix + (k,))


def _set(data, path, value):
    node = data
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value


SPEC_PATHS = list(_paths(NEURO_DATA)) + [("extra",), ("body", "extra"), ("helix", "pitch_deg_per_mm"),
                                         ("channels", "circle_diameter"), ("helix", "offset_top_deg")]


@FUZZ
@given(edits=st.lists(st.tuples(st.sampled_from(SPEC_PATHS), ANY_VALUE), min_size=1, max_size=3))
def test_mutated_specs_give_a_spec_or_a_one_line_error(edits):
    data = copy.deepcopy(NEURO_DATA)
    for path, value in edits:
        try:
            _set(data, path, value)
        except (TypeError, KeyError):
            pass  # a parent was replaced by a non-mapping earlier
    try:
        spec = parse_spec(data, "fuzz.yaml")
    except SpecError as exc:
        assert_one_line(exc, "fuzz.yaml: ")
        return
    assert finite_numbers(spec.model_dump())
    assert 1 <= len(spec.name) <= 64
    family = family_of(spec)
    geom = family.geometry(spec)
    build_violations(spec, geom, spec.imaging.pixel_size, family.length_key)  # the printability rules run on any valid spec


@FUZZ
@given(cuts=st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 40),
                               st.text(alphabet=":-[]{}&*!|>'\"#%@`,?\n .0123456789eEinfa", max_size=12)),
                     min_size=1, max_size=4))
def test_mutated_spec_text_gives_a_spec_or_a_one_line_error(cuts):
    text = NEURO.read_text()
    for pos, length, insert in cuts:
        pos %= len(text) + 1
        text = text[:pos] + insert + text[pos + length:]
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "spec.yaml"
        path.write_text(text)
        try:
            spec = load_spec(path)
        except SpecError as exc:
            assert_one_line(exc, str(path))
            return
    assert finite_numbers(spec.model_dump())
