"""Property-based: mutated geometry data and geometry file text give a geometry or a one-line GeometryFileError.

Seeded (``derandomize``), modest example counts and a per-example deadline that catches a hang.
"""

from __future__ import annotations

import copy

import pytest
from hypothesis import given
from hypothesis import strategies as st

from chic_register.errors import GeometryFileError
from chic_register.model.geometry import content_sha256, geometry_from_dict, load_geometry
from tests.helpers import ANY_VALUE, FUZZ, assert_one_line, finite_numbers


@pytest.fixture(scope="module")
def geometry_data(neuro_geometry):
    return neuro_geometry.to_dict()


GEOMETRY_KEYS = st.sampled_from(["version", "name", "units", "source", "body", "tubes", "format",
                                 "body.length", "body.outer_diameter", "body.inner_diameter",
                                 "tube.diameter", "tube.p0", "tube.p1", "tube.radius", "tube.pitch_deg_per_mm",
                                 "tube.z0", "tube.z1", "tube.kind", "tube.role", "tube.id", "tube.theta0_deg"])


@FUZZ
@given(edits=st.lists(st.tuples(GEOMETRY_KEYS, st.integers(0, 9), ANY_VALUE), min_size=1, max_size=3),
       rehash=st.booleans())
def test_mutated_geometry_gives_a_geometry_or_a_one_line_error(geometry_data, edits, rehash):
    data = copy.deepcopy(geometry_data)
    for key, tube_index, value in edits:
        if key.startswith("tube."):
            tubes = [t for t in data.get("tubes", []) if isinstance(t, dict)] if isinstance(data.get("tubes"), list) else []
            if tubes:
                tubes[tube_index % len(tubes)][key[5:]] = value
        elif key.startswith("body.") and isinstance(data.get("body"), dict):
            data["body"][key[5:]] = value
        else:
            data[key] = value
    if rehash:
        try:
            data["sha256"] = content_sha256(data)
        except (TypeError, ValueError):
            pass
    try:
        geom = geometry_from_dict(data, "g.yaml")
    except GeometryFileError as exc:
        assert_one_line(exc, "g.yaml: ")
        return
    # a geometry that loads is usable: finite, inside its plausible space, JSON-ready
    assert geom.body.inner_diameter < geom.body.outer_diameter
    content = geom.to_dict()
    assert finite_numbers(content)
    geom.intersect_plane((0.0, 0.0, geom.body.length / 2), (0.0, 0.0, 1.0))


@FUZZ
@given(cuts=st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 20),
                               st.text(alphabet=":-[]{}&*!|>'\"#\n .0123456789eEinf", max_size=10)),
                     min_size=1, max_size=3))
def test_mutated_geometry_text_gives_a_geometry_or_a_one_line_error(tmp_path, neuro_geometry_file, cuts):
    text = neuro_geometry_file.read_text()
    for pos, length, insert in cuts:
        pos %= len(text) + 1
        text = text[:pos] + insert + text[pos + length:]
    path = tmp_path / "mutated.yaml"
    path.write_text(text)
    for check_hash in (True, False):
        try:
            load_geometry(path, check_hash=check_hash)
        except GeometryFileError as exc:
            assert_one_line(exc, str(path))
