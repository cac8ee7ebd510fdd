"""The one atomic writer every output goes through."""

import os
import stat

import pytest

from chic_register.errors import OutputError
from chic_register.util.atomic import atomic_path, write_json


def test_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "out" / "truth.json"
    target.parent.mkdir()
    write_json(target, {"a": 1})
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half a fil")
            raise RuntimeError("disk full")
    assert target.read_text() == '{\n  "a": 1\n}\n'
    assert sorted(p.name for p in target.parent.iterdir()) == ["truth.json"]


def test_temporary_keeps_the_suffix_for_format_sniffing_writers(tmp_path):
    with atomic_path(tmp_path / "vol.nii.gz", suffix=".nii.gz") as tmp:
        assert tmp.name.endswith(".nii.gz") and tmp.parent == tmp_path
        tmp.write_bytes(b"x")
    assert (tmp_path / "vol.nii.gz").read_bytes() == b"x"


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o002, 0o664), (0o077, 0o600)])
def test_outputs_get_the_umask_permissions_not_mkstemps_0600(tmp_path, umask, mode):
    old = os.umask(umask)
    try:
        out = write_json(tmp_path / "x.json", {"a": 1})
    finally:
        os.umask(old)
    assert stat.S_IMODE(out.stat().st_mode) == mode


def test_missing_parent_folder_is_an_error_and_is_not_created(tmp_path):
    target = tmp_path / "nonexistent" / "dir" / "x.json"
    with pytest.raises(OutputError, match="does not exist"):
        write_json(target, {})
    assert not (tmp_path / "nonexistent").exists()
    (tmp_path / "file").write_text("")
    with pytest.raises(OutputError, match="is not a folder"):
        write_json(tmp_path / "file" / "x.json", {})
