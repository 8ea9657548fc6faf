"""Bad SOG, streamed SOG and .splat files: an error (a ``ValueError`` subclass) naming the file and the field,
exit 2 from ``scenesplat-stereo render`` with one line and nothing written; teacher discovery rejects a
teacher folder whose only scene is broken, naming it (docs/bad_input.md)."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
from tests.scenesplat_stereo.scene.test_lod import make_streamed

from scenesplat_stereo.cli import main
from scenesplat_stereo.scene.scene_files import load_scene
from scenesplat_stereo.scene.teachers import OrbitSpec, discover_teachers
from tests.support.bad_input import refusal, snapshot
from tests.support.sog_helpers import make_sog


def sog_zip(tmp: Path, edit=None, drop: str | None = None, replace: dict | None = None) -> bytes:
    """A good bundled SOG (SH 1, 37 Gaussians) with meta.json edited by ``edit(meta)``, member ``drop`` left out
    and members replaced by ``replace`` (name -> bytes)."""
    sog = make_sog(tmp / "src", 37, 1)
    meta = sog["meta"]
    if edit:
        edit(meta)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for name in [*sog["images"], "meta.json"]:
            if name == drop:
                continue
            data = json.dumps(meta).encode() if name == "meta.json" else (tmp / "src" / name).read_bytes()
            z.writestr(name, (replace or {}).get(name, data))
    return buf.getvalue()


def splat(edit=None) -> bytes:
    """Four good .splat records, edited by ``edit(records)``."""
    rec = np.zeros(4, np.dtype([("m", "<f4", 3), ("s", "<f4", 3), ("c", "u1", 4), ("q", "u1", 4)]))
    rec["s"], rec["c"], rec["q"] = 0.1, 200, [255, 128, 128, 128]
    if edit:
        edit(rec)
    return rec.tobytes()


def _set(d: dict, path: str, value) -> None:
    *head, last = path.split(".")
    for k in head:
        d = d[k]
    d[last] = value


SOG_CASES = [  # (name, bytes(tmp), part of the message)
    ("truncated", lambda t: sog_zip(t)[:3000], "not a zip file, or a truncated one"),
    ("wrong_magic", lambda t: b"GIF89a" + sog_zip(t)[6:], "means.files[0] 'means_l.webp': cannot read (Bad magic"),
    ("not_a_zip", lambda t: b"GIF89a" + bytes(100), "not a zip file"),
    ("no_meta_json", lambda t: sog_zip(t, drop="meta.json"), "no meta.json in the zip"),
    ("missing_image", lambda t: sog_zip(t, drop="quats.webp"), "quats.files[0] 'quats.webp': no such image"),
    ("image_not_webp", lambda t: sog_zip(t, replace={"scales.webp": b"not an image"}),
     "scales.files[0] 'scales.webp': not a readable WebP image"),
    ("meta_not_json", lambda t: sog_zip(t, replace={"meta.json": b"{nope"}), "meta.json: not JSON"),
    ("count_too_big", lambda t: sog_zip(t, lambda m: m.update(count=1000)), "fewer than the 1000 Gaussians"),
    ("count_zero", lambda t: sog_zip(t, lambda m: m.update(count=0)), "count: expected a positive whole number"),
    ("version_3", lambda t: sog_zip(t, lambda m: m.update(version=3)), "version: 3 is not supported"),
    ("nan_codebook", lambda t: sog_zip(t, lambda m: _set(m, "scales.codebook", [float("nan")] * 256)),
     "scales.codebook: non-finite value"),
    ("short_codebook", lambda t: sog_zip(t, lambda m: _set(m, "sh0.codebook", [0.0] * 10)),
     "sh0.codebook: expected 256 256 codebook numbers"),
    ("means_overflow", lambda t: sog_zip(t, lambda m: _set(m, "means.maxs", [1e3, 1e3, 1e3])),
     "Gaussians decode to non-finite values"),
    ("bands_5", lambda t: sog_zip(t, lambda m: _set(m, "shN.bands", 5)), "shN.bands: expected 1, 2 or 3"),
    ("palette_too_big", lambda t: sog_zip(t, lambda m: _set(m, "shN.count", 999)),
     "does not hold shN.count 999 centroids"),
]
SPLAT_CASES = [
    ("truncated", lambda t: splat()[:-5], "size 123 bytes is not a positive multiple of the 32-byte"),
    ("empty", lambda t: b"", "size 0 bytes is not a positive multiple"),
    ("nan_position", lambda t: splat(edit=lambda r: r["m"].__setitem__((2, 1), np.nan)),
     "means: 1 of 4 Gaussians decode to non-finite values (the first is Gaussian 2)"),
    ("zero_scale", lambda t: splat(edit=lambda r: r["s"].__setitem__((1, 0), 0.0)),
     "scales: 1 Gaussians have a scale <= 0"),
    ("inf_scale", lambda t: splat(edit=lambda r: r["s"].__setitem__((3, 2), np.inf)), "log_scales: 1 of 4 Gaussians"),
]
CASES = [(f"sog_{n}", "scene.sog", w, m) for n, w, m in SOG_CASES] + \
        [(f"splat_{n}", "scene.splat", w, m) for n, w, m in SPLAT_CASES]


@pytest.mark.parametrize("name,filename,write,message", CASES, ids=[c[0] for c in CASES])
def test_bad_scene_file_is_named_and_render_exits_2(tmp_path, capsys, name, filename, write, message) -> None:
    path = tmp_path / filename
    path.write_bytes(write(tmp_path))
    before = path.read_bytes()
    with pytest.raises(ValueError, match=filename) as info:
        load_scene(path)
    assert message in str(info.value), str(info.value)
    rc, err = refusal(main, ["render", path, "--out", tmp_path / "out", "--device", "cpu",
                             "--orbit", "radius=2,frames=1,size=16x12"], capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1 and message in err and str(path) in err, err
    assert not (tmp_path / "out").exists() and path.read_bytes() == before


def _lod_edit(root: Path, change) -> None:
    meta = json.loads((root / "lod-meta.json").read_text())
    change(meta)
    (root / "lod-meta.json").write_text(json.dumps(meta))


LOD_CASES = [
    ("missing_unit", lambda r: (r / "0_1" / "meta.json").unlink(), "0_1/meta.json: cannot read"),
    ("not_json", lambda r: (r / "lod-meta.json").write_text("{"), "lod-meta.json: not JSON"),
    ("levels_zero", lambda r: _lod_edit(r, lambda m: m.update(lodLevels=0)), "lodLevels: expected a whole number >= 1"),
    ("file_index", lambda r: _lod_edit(r, lambda m: m["tree"]["children"][2]["lods"]["0"].update(file=9)),
     "tree.children[2].lods['0']: expected a level < lodLevels"),
    ("counts", lambda r: _lod_edit(r, lambda m: m.update(counts=[49, 12])), "counts: [49, 12] but the tree references"),
    ("past_end", lambda r: _lod_edit(r, lambda m: (m["tree"]["children"][2]["lods"]["0"].update(count=25),
                                                   m.pop("counts"))), "rows 0..24 of"),
]


@pytest.mark.parametrize("name,breaker,message", LOD_CASES, ids=[c[0] for c in LOD_CASES])
def test_bad_streamed_scene_is_named_and_render_exits_2(tmp_path, capsys, name, breaker, message) -> None:
    root, _ = make_streamed(tmp_path / "scene")
    breaker(root)
    before = snapshot(root)
    with pytest.raises(ValueError, match="meta.json") as info:
        load_scene(root)
    assert message in str(info.value), str(info.value)
    rc, err = refusal(main, ["render", root / "lod-meta.json", "--out", tmp_path / "out", "--device", "cpu",
                             "--orbit", "radius=2,frames=1,size=16x12"], capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1 and message in err, err
    assert not (tmp_path / "out").exists() and snapshot(root) == before


def test_teacher_folder_with_a_broken_scene_file_is_rejected(tmp_path) -> None:
    (tmp_path / "teachers" / "good").mkdir(parents=True)
    (tmp_path / "teachers" / "good" / "g.sog").write_bytes(sog_zip(tmp_path))
    (tmp_path / "teachers" / "bad").mkdir()
    (tmp_path / "teachers" / "bad" / "b.splat").write_bytes(splat()[:-5])
    found = discover_teachers(tmp_path / "teachers", OrbitSpec(radius=2.0))
    assert [t.scene_id for t in found.teachers] == ["good"] and found.teachers[0].sh_degree == 1
    assert len(found.rejected) == 1 and "b.splat: header:" in found.rejected[0].reason
    assert "not a positive multiple of the 32-byte" in found.rejected[0].reason
