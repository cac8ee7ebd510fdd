"""How both programs end when their reader leaves: no traceback, exit 0 or 141 (SIGPIPE)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("argv", [
    [sys.executable, "-m", "chic_design.cli", "schema"],
    [sys.executable, "-m", "chic_register.cli.main", "--help"],
])
def test_a_closed_stdout_is_no_traceback(argv):
    p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)
    p.stdout.close()  # the reader (`| head`) left before the output came
    _, err = p.communicate(timeout=60)
    assert b"Traceback" not in err, err.decode()
    assert p.returncode in (0, 141)
