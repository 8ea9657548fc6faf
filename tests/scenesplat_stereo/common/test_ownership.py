"""The one owner of "may this command replace what is there" for a single-file output
(``scenesplat_stereo.common.ownership.check_replaceable_file`` and ``write_owned_file``, both held by
``OwnedFile``): its own manifest beside it, in the format of a folder's; the folder checks do not count that
manifest as a file. And the symbolic links a command makes in its folder (COLMAP's staged images), recorded as links."""

from __future__ import annotations

import json

import pytest

from scenesplat_stereo.common.ownership import (OWNER_FILE, OwnedFile, OwnedFolder, check_replaceable_file,
                                                foreign_file, write_manifest, write_owned_file)


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


def test_an_owned_file_is_checked_when_made_and_written_when_the_work_is_done(tmp_path):
    assert OwnedFile(None, "--out", "tool a").write("text") is None and list(tmp_path.iterdir()) == []  # none asked
    report = OwnedFile(tmp_path / "new" / "report.md", "--out", "tool a")
    assert list(tmp_path.iterdir()) == []  # checking creates nothing
    assert report.write("naïve\n") == tmp_path / "new" / "report.md"
    assert (tmp_path / "new" / "report.md").read_text(encoding="utf-8") == "naïve\n"
    assert OwnedFile(tmp_path / "new" / "report.md", "--out", "tool a").write(b"again") is not None  # its own
    (tmp_path / "mine.md").write_text("the user's")
    with pytest.raises(ValueError, match=r"--out .*mine.md: exists and was not written by `tool a`"):
        OwnedFile(tmp_path / "mine.md", "--out", "tool a")  # refused when made, before any work
    assert (tmp_path / "mine.md").read_text() == "the user's"


def test_a_link_the_command_made_is_its_own_and_a_changed_link_is_not(tmp_path):
    (tmp_path / "a.png").write_bytes(b"a")
    (tmp_path / "b.png").write_bytes(b"a")  # the same bytes: the link's target is what counts
    out = tmp_path / "work"
    with OwnedFolder(out, "tool a"):
        (out / "images").mkdir()
        (out / "images" / "0.png").symlink_to(tmp_path / "a.png")
        (out / "db").write_bytes(b"db")
    assert json.loads((out / OWNER_FILE).read_text())["files"]["images/0.png"] == {"link": str(tmp_path / "a.png")}
    assert foreign_file(out, "tool a") is None  # a rerun may replace it
    (out / "images" / "0.png").unlink()
    (out / "images" / "0.png").symlink_to(tmp_path / "b.png")
    assert foreign_file(out, "tool a") == "holds 'images/0.png', changed since `tool a` wrote it"
    (out / "images" / "0.png").unlink()
    (out / "images" / "0.png").write_bytes(b"a")  # a file in place of the link
    assert foreign_file(out, "tool a") == "holds 'images/0.png', changed since `tool a` wrote it"
    (out / "images" / "0.png").unlink()
    (out / "images" / "0.png").symlink_to(tmp_path / "a.png")
    (out / "images" / "1.png").symlink_to(tmp_path / "b.png")  # a link of the user's
    assert foreign_file(out, "tool a") == "holds files not written by `tool a` (e.g. 'images/1.png')"
