"""Smaller things a newcomer meets (links, commands, messages, permissions), each pinned by a test."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")


def test_readme_links_stay_inside_the_repository():
    links = re.findall(r"\]\(([^)#\s]+)", README)
    local = [x for x in links if not x.startswith(("http://", "https://", "mailto:"))]
    assert "docs/interfaces.md" in local
    for link in local:
        target = (ROOT / link).resolve()
        assert target.is_relative_to(ROOT) and target.exists(), link


def test_readme_defines_G_before_using_it():
    blocks = re.findall(r"```(?:sh|console)\n(.*?)```", README, flags=re.S)
    assert not any("--geometry G " in b for b in blocks)  # shell commands use $G, defined first
    first = next(b for b in blocks if "$G" in b)
    assert re.search(r"^(\$ )?G=\S+geometry.yaml$", first[: first.index("$G")], flags=re.M), first[:200]


def test_interfaces_doc_keeps_the_contract_and_adds_the_decisions():
    doc = (ROOT / "docs" / "interfaces.md").read_text(encoding="utf-8")
    for heading in ("## 1. The fiducial frame F", "## 2. The geometry file", "## 3. Image coordinates",
                    "## 4. Commands and their JSON", "## 5. 3D Slicer, OpenIGTLink and robots"):
        assert heading in doc
    for fact in ("SPACE=LPS", "CHICToRAS", "CHICTool", "T_scanner_from_tool", "exit code is 4"):
        assert fact in doc


@pytest.mark.parametrize("ratio, text", [(3.21, "3.2x better"), (1.0, "1.0x better"), (0.7, "1.4x worse"),
                                         (0.25, "4.0x worse")])
def test_evaluate_says_worse_when_worse(ratio, text):
    from chic_register.studies.evaluate import versus_paper

    assert versus_paper(ratio) == text




