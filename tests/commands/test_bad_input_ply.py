"""Bad ``.ply`` files: ``PlyError`` naming the file and the element/property/line; the file is untouched."""

from __future__ import annotations

from pathlib import Path

import pytest

from scenesplat_stereo.scene.gaussians import PlyError, load_ply

PROPS = "x y z f_dc_0 f_dc_1 f_dc_2 opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3".split()
ROW = "0 0 1 0.1 0.2 0.3 0.5 -2 -2 -2 1 0 0 0"


def ascii_ply(n_rows: int = 2, header_extra: str = "", rows: list[str] | None = None, props=PROPS,
              count: int | None = None, fmt: str = "ascii") -> bytes:
    head = ["ply", f"format {fmt} 1.0", f"element vertex {n_rows if count is None else count}"]
    head += [f"property float {p}" for p in props]
    head += [header_extra] if header_extra else []
    head += ["end_header"]
    body = rows if rows is not None else [ROW] * n_rows
    return ("\n".join(head + body) + "\n").encode()


CASES = [  # (file bytes, part of the message)
    (b"plx\nformat ascii 1.0\nend_header\n", "not a PLY file"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\n", "no 'end_header' line"),
    (ascii_ply(fmt="binary_middle_endian"), "unsupported format 'binary_middle_endian'"),
    (ascii_ply(props=PROPS + ["x"]), "property 'x' is declared twice"),
    (ascii_ply(header_extra="element vertex 3\nproperty float x"), "element 'vertex' is declared twice"),
    (ascii_ply(rows=[ROW, ROW, ROW]), "declares 2 rows but the body has 1 more"),
    (ascii_ply(rows=[ROW]), "body truncated: element 'vertex' needs 2 lines"),
    (ascii_ply(rows=[ROW, ROW + " 7"]), "element 'vertex' row 1 has 15 values"),
    (ascii_ply(rows=[ROW, ROW.replace("0.5", "abc")]), "non-numeric value"),
    (ascii_ply(props=[p for p in PROPS if p != "opacity"], rows=[ROW.rsplit(" ", 1)[0]] * 2),
     "lacks required properties opacity"),
    (ascii_ply(props=PROPS + [f"f_rest_{i}" for i in range(5)]), "5 f_rest_* properties"),
    (b"ply\nformat ascii 1.0\nelement face 1\nproperty float x\nend_header\n1\n", "no element 'vertex'"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 2\n" + "".join(f"property float {p}\n" for p in PROPS)
     .encode() + b"end_header\n" + b"\0" * 20, "body truncated"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float\nend_header\n", "malformed"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\nend_header\n", "unknown type 'quad'"),
    (b"ply\nelement vertex 1\nproperty float x\nend_header\n", "no 'format' line"),
]


@pytest.mark.parametrize("data,message", CASES, ids=[c[1][:40] for c in CASES])
def test_bad_ply_is_named(tmp_path: Path, data: bytes, message: str) -> None:
    path = tmp_path / "scene.ply"
    path.write_bytes(data)
    with pytest.raises(PlyError, match="scene.ply") as info:
        load_ply(path)
    assert message in str(info.value), str(info.value)
    assert path.read_bytes() == data


def test_good_ascii_ply_reads(tmp_path: Path) -> None:
    """The baseline the cases above break: this file reads."""
    path = tmp_path / "scene.ply"
    path.write_bytes(ascii_ply())
    assert len(load_ply(path)) == 2
