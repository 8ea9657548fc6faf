"""The one owner of "may this command replace what is there" for a single-file output
(``scenesplat_stereo.common.files.check_replaceable_file`` and ``write_owned_file``): its own manifest beside it,
in the format of a folder's; the folder checks do not count that manifest as a file."""

from __future__ import annotations

import json

import pytest

from scenesplat_stereo.common.files import (OWNER_FILE, check_replaceable_file, foreign_file, write_manifest,
                                            write_owned_file)


def test_a_single_file_output_is_replaced_only_while_its_owner_wrote_it(tmp_path):
    sheet = tmp_path / "sheet.png"
    assert check_replaceable_file(sheet, "--sheet", "tool a") == sheet and list(tmp_path.iterdir()) == []  # none made
    write_owned_file(sheet, b"first", "tool a")
    manifest = json.loads((tmp_path / f"{OWNER_FILE}.sheet.png").read_text())
    assert manifest["owner"] == "tool a" and "open" not in manifest and manifest["files"]["sheet.png"]["size"] == 5
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"{OWNER_FILE}.sheet.png", "sheet.png"]  # no temp file
    assert check_replaceable_file(sheet, "--sheet", "tool a") == sheet
    with pytest.raises(ValueError, match=r"--sheet .*sheet.png: exists and is the output of `tool a`, and `tool b` "
                                         r"replaces only what it wrote; choose another --sheet"):
        check_replaceable_file(sheet, "--sheet", "tool b")
    sheet.write_bytes(b"edited")
    with pytest.raises(ValueError, match="exists and changed since `tool a` wrote it"):
        check_replaceable_file(sheet, "--sheet", "tool a")
    mine = tmp_path / "mine.png"
    mine.write_bytes(b"the user's")
    with pytest.raises(ValueError, match=r"was not written by `tool a` \(no \.written-by\.mine\.png beside it\)"):
        check_replaceable_file(mine, "--sheet", "tool a")
    with pytest.raises(ValueError, match="is a folder"):
        check_replaceable_file(tmp_path, "--sheet", "tool a")


def test_a_run_killed_while_writing_its_file_may_replace_it(tmp_path):
    sheet = tmp_path / "sheet.png"
    write_owned_file(sheet, b"first", "tool a")
    (tmp_path / f"{OWNER_FILE}.sheet.png").write_text(json.dumps({"owner": "tool a", "files": {}, "open": True}))
    sheet.write_bytes(b"half of the second")  # what a kill between the manifest's two writes can leave
    assert check_replaceable_file(sheet, "--sheet", "tool a") == sheet
    with pytest.raises(ValueError, match="is the output of `tool a`"):
        check_replaceable_file(sheet, "--sheet", "tool b")


def test_a_symlinked_file_is_written_through(tmp_path):
    (tmp_path / "real").mkdir()
    write_owned_file(tmp_path / "real" / "sheet.png", b"first", "tool a")
    (tmp_path / "link.png").symlink_to(tmp_path / "real" / "sheet.png")
    target = check_replaceable_file(tmp_path / "link.png", "--sheet", "tool a")
    assert target == tmp_path / "real" / "sheet.png"
    write_owned_file(target, b"second", "tool a")
    assert (tmp_path / "link.png").is_symlink() and (tmp_path / "link.png").read_bytes() == b"second"


def test_a_folder_owner_sees_the_file_but_not_its_manifest(tmp_path):
    write_owned_file(tmp_path / "sheet.png", b"x", "tool a")
    assert foreign_file(tmp_path, "tool b") == "holds files not written by `tool b` (e.g. 'sheet.png')"
    write_manifest(tmp_path, "tool b")
    assert list(json.loads((tmp_path / OWNER_FILE).read_text())["files"]) == ["sheet.png"]
