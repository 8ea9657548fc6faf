"""scenesplat_stereo.scene.scene_files (every format by name, read back by its first bytes), and our files checked
against real clients: PlayCanvas splat-transform (its compressed .ply writer, Niantic's SPZ encoder through
@adobe/spz, its readers) and the SuperSplat viewer's settings validator. The client tests need node and
``npm install`` in scripts/checks/viewer (docs/model.md "Scene files"); they skip with the reason otherwise."""

from __future__ import annotations

import gzip
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from scenesplat_stereo.scene.compressed_ply import morton_order
from scenesplat_stereo.scene.gaussians import PlyError, load_ply, save_ply
from scenesplat_stereo.scene.scene_files import FORMATS, load_scene, save_scene
from scenesplat_stereo.scene.spz import encode_spz
from sgmodel.predict.viewers import supersplat_settings
from tests.support.paths import REPO
from tests.support.ply_helpers import random_scene

VIEWER = REPO / "scripts" / "checks" / "viewer"
SPLAT_TRANSFORM = VIEWER / "node_modules" / "@playcanvas" / "splat-transform" / "bin" / "cli.mjs"


@pytest.mark.parametrize("name", sorted(FORMATS))
def test_every_format_round_trips_by_its_first_bytes(tmp_path: Path, name: str) -> None:
    scene = random_scene(np.random.default_rng(0), 300, 1)
    path = save_scene(scene, tmp_path / f"s{FORMATS[name].suffix}", name)
    back = load_scene(path)
    assert len(back) == 300 and back.sh_degree == 1
    order = morton_order(scene.means) if name in ("compressed-ply", "sog") else np.arange(300)
    m = scene.means.astype(np.float64)  # SOG: 16 bits of t = sign(x) ln(|x| + 1) over its range, dx/dt = e^|t|
    t = np.sign(m) * np.log1p(np.abs(m))
    sog_step = float((np.exp(np.abs(t).max()) * (t.max(0) - t.min(0)) / 65535 / 2).max()) * 1.01 + 1e-6
    step = {"ply": 0.0, "spz": 2.0**-13, "spz-parallel": 2.0**-13, "compressed-ply": 1e-2,
            "sog": sog_step}[name]  # half a step;
    assert np.abs(back.means - scene.means[order]).max() <= step  # compressed: 10 bits over a chunk box of
    # random points metres apart
    moved = tmp_path / "no_suffix"
    shutil.copy(path, moved)
    assert len(load_scene(moved)) == 300  # the name does not matter


def test_unknown_format_and_file(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unknown scene format 'splat'"):
        save_scene(random_scene(np.random.default_rng(0), 3, 0), tmp_path / "x", "splat")
    (tmp_path / "x.bin").write_bytes(b"\x00\x01junk")
    with pytest.raises(PlyError, match="not a scene file this reads"):
        load_scene(tmp_path / "x.bin")


def test_compact_formats_are_smaller(tmp_path: Path) -> None:
    """Bytes per Gaussian: .ply 4 (17 + 3 (K-1)); compressed 16 + 3 (K-1) (+ 72 per 256); spz before gzip
    20 + 3 (K-1) (9 + 1 + 3 + 3 + 4)."""
    for degree in (0, 2):
        scene = random_scene(np.random.default_rng(degree), 4096, degree)
        sizes = {n: save_scene(scene, tmp_path / f"{degree}{f.suffix}", n).stat().st_size for n, f in FORMATS.items()}
        k = 3 * ((degree + 1) ** 2 - 1)
        assert sizes["ply"] - 4 * (17 + k) * 4096 < 2000  # the header
        assert sizes["compressed-ply"] - (16 + k) * 4096 - 72 * 16 < 3000
        assert len(gzip.decompress((tmp_path / f"{degree}.spz").read_bytes())) == 16 + (20 + k) * 4096


# ---------------------------------------------------------------- real clients (optional)

def splat_transform(*args: str) -> subprocess.CompletedProcess:
    if shutil.which("node") is None:
        pytest.skip("node is not installed (the splat-transform checks need it)")
    if not SPLAT_TRANSFORM.is_file():
        pytest.skip(f"{SPLAT_TRANSFORM} is absent: run `npm install` in {VIEWER}")
    run = subprocess.run(["node", str(SPLAT_TRANSFORM), "-q", "-w", *args], capture_output=True, text=True,
                         timeout=300, check=False)
    assert run.returncode == 0, run.stderr
    return run


def _without_comments(data: bytes) -> bytes:
    head, body = data.split(b"end_header\n", 1)
    return b"\n".join(line for line in head.split(b"\n") if not line.startswith(b"comment")) + b"end_header\n" + body


def test_compressed_writer_is_bit_identical_to_splat_transform(tmp_path: Path, guitar_ply: Path) -> None:
    """The real guitar through both writers: the same bytes except splat-transform's header comment."""
    ours = FORMATS["compressed-ply"].save(load_ply(guitar_ply), tmp_path / "ours.compressed.ply")
    splat_transform(str(guitar_ply), str(tmp_path / "theirs.compressed.ply"))
    assert _without_comments((tmp_path / "theirs.compressed.ply").read_bytes()) == ours.read_bytes()


def test_compressed_writer_takes_splat_transforms_signed_zero_bounds(tmp_path: Path) -> None:
    """Chunk bounds at zero: -0 where a -0 is among a chunk's smallest values, +0 where a +0 is among its largest
    (JavaScript's Math.min and Math.max), the same bytes as splat-transform's."""
    rng = np.random.default_rng(1)
    scene = random_scene(rng, 3000, 1)
    scene.means[:, 0], scene.means[:, 1] = np.abs(scene.means[:, 0]), -np.abs(scene.means[:, 1])
    for axis in range(3):
        scene.means[rng.integers(0, 3000, 600), axis] = rng.choice([0.0, -0.0], 600)
    save_ply(scene, tmp_path / "s.ply")
    ours = FORMATS["compressed-ply"].save(load_ply(tmp_path / "s.ply"), tmp_path / "ours.compressed.ply")
    splat_transform(str(tmp_path / "s.ply"), str(tmp_path / "theirs.compressed.ply"))
    assert _without_comments((tmp_path / "theirs.compressed.ply").read_bytes()) == ours.read_bytes()


def test_spz_encoding_is_niantics(tmp_path: Path) -> None:
    """splat-transform --spz-version 3 runs Niantic's encoder (the @adobe/spz WebAssembly build of
    nianticlabs/spz) on our .ply; its uncompressed stream equals ours byte for byte."""
    rng = np.random.default_rng(3)
    scene = random_scene(rng, 2000, 3)
    scene.sh[:, 1:] = np.clip(scene.sh[:, 1:], -1.2, 1.2)
    save_ply(scene, tmp_path / "s.ply")
    splat_transform(str(tmp_path / "s.ply"), "--spz-version", "3", str(tmp_path / "theirs.spz"))
    assert gzip.decompress((tmp_path / "theirs.spz").read_bytes()) == encode_spz(scene)


@pytest.mark.parametrize("name", ["compressed-ply", "spz", "spz-parallel"])
def test_splat_transform_reads_our_files_as_we_do(tmp_path: Path, name: str, monkeypatch) -> None:
    """Our compact file converted to .ply by splat-transform decodes to what our reader decodes (the same bits:
    float32 rounding). Opacities stay inside (0, 1): splat-transform writes the alpha bytes 0 and 255 of a
    compressed file as infinite logits (and clamps them for .spz). The parallel .spz in pieces of 4 KiB: eight
    of them, seven sync-flushed."""
    from scenesplat_stereo.scene import spz

    monkeypatch.setattr(spz, "DEFLATE_PIECE", 4096)
    scene = random_scene(np.random.default_rng(4), 700, 2)
    scene.opacities[:] = np.clip(scene.opacities, 0.01, 0.99)
    ours = save_scene(scene, tmp_path / f"s{FORMATS[name].suffix}", name)
    splat_transform(str(ours), str(tmp_path / "back.ply"))
    a, b = load_scene(ours), load_ply(tmp_path / "back.ply")
    assert len(a) == len(b) == 700 and a.sh_degree == b.sh_degree == 2
    np.testing.assert_allclose(b.means, a.means, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(b.scales, a.scales, rtol=1e-5)
    np.testing.assert_allclose(b.sh, a.sh, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.abs((b.quats * a.quats).sum(1)), 1.0, atol=1e-6)
    np.testing.assert_allclose(b.opacities, a.opacities, atol=1.1e-6)


def test_supersplat_viewer_accepts_our_settings(tmp_path: Path) -> None:
    """validateSettings of @playcanvas/supersplat-viewer/settings with its authoring limits on."""
    if shutil.which("node") is None:
        pytest.skip("node is not installed")
    if not (VIEWER / "node_modules" / "@playcanvas" / "supersplat-viewer").is_dir():
        pytest.skip(f"@playcanvas/supersplat-viewer is absent: run `npm install` in {VIEWER}")
    K = np.array([[280.0, 0, 160], [0, 280.0, 128], [0, 0, 1]])
    settings = supersplat_settings(np.eye(4), K, 320, 256, focus=3.8)
    (tmp_path / "settings.json").write_text(json.dumps(settings))
    script = ("import('@playcanvas/supersplat-viewer/settings').then(m => { const s = JSON.parse("
              "require('fs').readFileSync(process.argv[1], 'utf8')); m.validateSettings(s, { limits: true }); "
              "console.log(JSON.stringify(m.importSettings(s).cameras[0].initial)); })")
    run = subprocess.run(["node", "-e", script, str(tmp_path / "settings.json")], capture_output=True, text=True,
                         cwd=VIEWER, timeout=60, check=False)
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout) == settings["cameras"][0]["initial"]
