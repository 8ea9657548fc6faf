"""scenesplat_stereo.scene.sog: the reader against a float64 decode written from the format description
(tests/support/sog_helpers.py) for versions 1 and 2, bundled and not, SH degrees 0-3; against PlayCanvas
splat-transform 3.7.0's decode of the real captures (tests/data/captures, made by scripts/inputs/capture_samples.py);
the writer's round trip and splat-transform reading our files; the writer's quantisers (``palettes``, the quaternion
texels) against plain float64 / row-by-row versions, its bytes against a run on one thread, and its texels on a GPU
against those on the CPU."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import torch

from scenesplat_stereo.scene import palettes, row_tasks, sog_texels
from scenesplat_stereo.scene.compressed_ply import morton_order
from scenesplat_stereo.scene.gaussians import GaussianScene, load_ply
from scenesplat_stereo.scene.scene_files import load_scene, scene_info
from scenesplat_stereo.scene.sog import encode_sog, load_sog, save_sog
from tests.support.paths import CAPTURES, SPLAT_TRANSFORM, TEST_DATA
from tests.support.ply_helpers import random_scene
from tests.support.sog_helpers import make_sog, reference_decode

DATA = TEST_DATA / "captures"


def assert_matches(scene: GaussianScene, means, quats, log_scales, opacities, sh, atol: float = 1e-5) -> None:
    """``scene`` equals the float64 arrays within float32 rounding (quats compared after normalising, up to sign)."""
    unit = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    close = lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-6, atol=atol)  # noqa: E731
    close(scene.means, means)
    assert np.minimum(np.abs(scene.quats - unit).max(1), np.abs(scene.quats + unit).max(1)).max() < atol
    close(np.log(scene.scales.astype(np.float64)), log_scales)
    close(scene.opacities, opacities)
    close(scene.sh, sh)


@pytest.mark.parametrize("version,degree,bundle", [(2, 0, True), (2, 1, False), (2, 2, True), (2, 3, True),
                                                   (1, 0, False), (1, 2, False), (1, 3, True)])
def test_reader_matches_the_format_description(tmp_path: Path, version: int, degree: int, bundle: bool) -> None:
    sog = make_sog(tmp_path / "scene", 37, degree, version, bundle)
    scene = load_scene(sog["path"])  # by its first bytes (zip) or as a folder holding meta.json
    assert (len(scene), scene.sh_degree) == (37, degree) == scene_info(sog["path"])
    assert_matches(scene, *reference_decode(sog))
    if not bundle:
        assert_matches(load_scene(sog["path"] / "meta.json"), *reference_decode(sog))


def _capture_samples() -> list[Path]:
    return sorted(p for p in DATA.glob("*.npz") if "-lod" not in p.name)


def check_against_sample(scene: GaussianScene, sample_path: Path) -> None:
    """``scene`` holds splat-transform's decode (float32 as it wrote them) at the sample's rows."""
    s = np.load(sample_path)
    assert len(scene) == int(s["count"])
    rows = s["rows"]
    sh = np.concatenate([s["f_dc"][:, None], s["f_rest"].reshape(len(rows), 3, -1).transpose(0, 2, 1)], 1)
    opacity = 1 / (1 + np.exp(-s["opacity"].astype(np.float64)))
    assert_matches(scene.subset(rows), s["xyz"], s["rot"].astype(np.float64), s["scale"], opacity, sh, atol=2e-6)


@pytest.mark.real_data
@pytest.mark.parametrize("sample", [p for p in _capture_samples() if p.stem not in ("plant", "tarot-box")],
                         ids=lambda p: p.stem)
def test_real_captures_match_splat_transform(sample: Path) -> None:
    files = list((CAPTURES / sample.stem).glob("*.sog"))
    if not files:
        pytest.skip(f"shared data not available: {CAPTURES / sample.stem} is absent (it lives beside the repository)")
    check_against_sample(load_scene(files[0]), sample)


def test_writer_round_trip(tmp_path: Path) -> None:
    """Read back within the format's steps: positions half a 16-bit step of sign(x) ln(|x| + 1) (times
    e^|t|), quaternion components half of 2 / 255 / sqrt(2) (then normalised), opacity half of 1/255, and every
    log-scale and colour on its codebook's nearest entry (colour: of Gaussians whose opacity byte is not 0); SH
    from the palette, closer than zero SH."""
    rng = np.random.default_rng(3)
    scene = random_scene(rng, 3000, 2)
    path = save_sog(scene, tmp_path / "s.sog")
    back, ref = load_sog(path), scene.subset(morton_order(scene.means))
    assert (len(back), back.sh_degree) == (3000, 2)
    m = ref.means.astype(np.float64)
    t = np.sign(m) * np.log1p(np.abs(m))
    assert (np.abs(back.means - m) <= np.exp(np.abs(t)) * (t.max(0) - t.min(0)) / 65535 / 2 * 1.001 + 1e-6).all()
    q = ref.quats / np.linalg.norm(ref.quats, axis=1, keepdims=True)
    assert np.minimum(np.abs(back.quats - q).max(1), np.abs(back.quats + q).max(1)).max() < 2 / 255
    assert np.abs(back.opacities - np.clip(ref.opacities, 1e-6, 1 - 1e-6)).max() <= 0.5 / 255 + 1e-6
    meta = json.loads(zipfile.ZipFile(path).read("meta.json"))
    seen = np.rint(ref.opacities * 255.0) > 0  # libwebp drops the colour of a texel whose alpha is 0
    assert not seen.all()
    for book, got, want in ((meta["scales"]["codebook"], np.log(back.scales), np.log(ref.scales.astype(np.float64))),
                            (meta["sh0"]["codebook"], back.sh[seen, 0], ref.sh[seen, 0])):
        nearest = np.abs(np.asarray(book)[None, None] - want[..., None]).min(-1)
        assert (np.abs(got - want) <= nearest + 1e-5).all()
    assert meta["shN"]["count"] == 2048 and meta["shN"]["bands"] == 2  # splat-transform's size for 3000
    assert np.sqrt(((back.sh[:, 1:] - ref.sh[:, 1:]) ** 2).mean()) < np.sqrt((ref.sh[:, 1:] ** 2).mean())


def test_writer_sh0_and_one_gaussian(tmp_path: Path) -> None:
    scene = random_scene(np.random.default_rng(1), 1, 0)
    back = load_sog(save_sog(scene, tmp_path / "one.sog"))
    np.testing.assert_allclose(back.means, scene.means, atol=1e-6)
    assert back.sh_degree == 0 and "shN" not in json.loads(zipfile.ZipFile(tmp_path / "one.sog").read("meta.json"))


@pytest.mark.skipif(not SPLAT_TRANSFORM.is_file() or shutil.which("node") is None,
                    reason="needs node and `npm ci` in scripts/checks/viewer (splat-transform 3.7.0)")
@pytest.mark.parametrize("degree", [0, 3])
def test_splat_transform_reads_our_sog(tmp_path: Path, degree: int) -> None:
    scene = random_scene(np.random.default_rng(degree), 500, degree)
    ours = load_sog(save_sog(scene, tmp_path / "s.sog"))
    subprocess.run(["node", str(SPLAT_TRANSFORM), "-w", str(tmp_path / "s.sog"), str(tmp_path / "s.ply")],
                   check=True, capture_output=True)
    theirs = load_ply(tmp_path / "s.ply")
    assert theirs.sh_degree == degree
    assert_matches(theirs, ours.means, ours.quats.astype(np.float64), np.log(ours.scales.astype(np.float64)),
                   ours.opacities, ours.sh, atol=2e-6)


def test_nearest_entry_is_the_binary_search() -> None:
    """``palettes.Nearest`` against ``np.searchsorted`` of the float64 midpoints (its definition) on books that are
    spread, rounded (duplicate entries), padded with their last entry, flat, of one entry, or narrow at a large
    magnitude (the exact fallback), with values on every midpoint and entry, one float step either side, and
    beyond the ends; and against the nearest entry by brute force in float64 away from midpoints."""
    rng = np.random.default_rng(4)
    books = [rng.normal(0, 1, 256), np.round(rng.normal(0, 1, 256), 1), np.r_[rng.normal(0, 1, 100), [3.0] * 156],
             np.full(256, 1.5), [0.25], 1e6 + rng.normal(0, 1e-9, 256), 1e3 + rng.normal(0, 1e-7, 256),
             1.0 + rng.normal(0, 1e-5, 256), np.r_[rng.normal(-8, 0.01, 128), rng.normal(2, 3, 128)]]
    for raw in books:
        book = np.sort(np.asarray(raw, np.float64)).astype(np.float32)
        b = book.astype(np.float64)
        mids = 0.5 * (b[1:] + b[:-1])
        values = np.concatenate([mids, np.nextafter(mids, np.inf), np.nextafter(mids, -np.inf), b,
                                 np.nextafter(b, np.inf), b[0] + (b[-1] - b[0]) * rng.random(5000),
                                 rng.normal(0, 20, 500), [-1e300, 1e300]])
        for shaped in (values, values[:len(values) // 3 * 3].reshape(-1, 3)):
            labels = palettes.Nearest(book)(shaped).numpy()
            assert labels.shape == shaped.shape and labels.dtype == np.uint8
            np.testing.assert_array_equal(labels, np.minimum(np.searchsorted(mids, shaped), len(b) - 1))
        finite = values[np.abs(values) < 1e100]  # |1e300 - entry| is 1e300 for every entry
        away = finite[np.abs(finite[:, None] - mids[None]).min(1, initial=np.inf) > 1e-9 * (1 + np.abs(finite))]
        brute = np.abs(away[:, None] - b[None]).argmin(1)  # the first of equal entries
        np.testing.assert_array_equal(b[palettes.Nearest(book)(away).numpy().astype(np.intp)], b[brute])


def test_codebook_histogram_is_numpys_but_at_the_edges() -> None:
    """``palettes.histogram`` against ``np.histogram`` over ranges of every scale, on random values and every bin
    edge: the same edges; the same counts for the values farther than a few float steps from every edge; with
    the values near an edge too, counts that differ from numpy's by at most those values moved one bin."""
    rng = np.random.default_rng(7)
    for trial in range(60):
        bins = int(rng.choice([1, 7, 256, 1 << 14]))
        x = rng.standard_normal(int(rng.integers(2, 4000))) * 10 ** rng.uniform(-6, 6) + rng.uniform(-1e3, 1e3)
        lo, hi = float(x.min()), float(x.max())
        edges = np.histogram_bin_edges(x, bins, (lo, hi))
        values = np.concatenate([x, edges])
        i = np.clip(np.searchsorted(edges, values), 1, bins)
        gap = np.minimum(np.abs(values - edges[i - 1]), np.abs(values - edges[i]))
        near = gap <= 8 * np.spacing(max(abs(lo), abs(hi)))
        for part, exact in ((values[~near], True), (values, False)):
            counts, got_edges = palettes.histogram(torch.from_numpy(part), bins, lo, hi)
            want = np.histogram(part, bins, (lo, hi))[0]
            np.testing.assert_array_equal(got_edges, edges)
            assert counts.sum() == len(part)
            if exact:
                np.testing.assert_array_equal(counts, want, err_msg=f"trial {trial}")
            else:
                assert np.abs(counts - want).sum() <= 2 * near.sum(), trial


def test_kmeans_labels_are_each_rows_nearest_centroid() -> None:
    """Every row's label is its nearest centroid by float64 brute force (up to float32 ties), and the palette
    is closer to the rows than one of k rows picked at random is."""
    rng = np.random.default_rng(6)
    x = (rng.normal(0, 0.1, (40, 24))[rng.integers(0, 40, 3000)] + rng.normal(0, 0.01, (3000, 24))).astype(np.float32)
    centroids, labels = palettes.kmeans(x, 256)
    assert centroids.shape == (256, 24) and labels.shape == (3000,)
    d = ((x.astype(np.float64)[:, None] - centroids.astype(np.float64)[None]) ** 2).sum(-1)
    assert (d[np.arange(3000), labels] <= d.min(1) * (1 + 1e-4) + 1e-9).all()
    picked = x[rng.choice(3000, 256, replace=False)].astype(np.float64)
    random_error = ((x[:, None] - picked[None]) ** 2).sum(-1).min(1).mean()
    assert d[np.arange(3000), labels].mean() < random_error


def test_kmeans_takes_a_tensor_and_draws_one_order_per_row_count() -> None:
    """A tensor gives the palette its array gives; the fit's random order is the seeded ``randperm`` of the row
    count, drawn once for every call with that count."""
    rng = np.random.default_rng(8)
    x = rng.normal(0, 0.1, (5000, 9)).astype(np.float32)
    want = palettes.kmeans(x, 64)
    for got in (palettes.kmeans(torch.from_numpy(x), 64), palettes.kmeans(x.astype(np.float64), 64)):
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
    assert torch.equal(palettes.permutation(5000), torch.randperm(5000, generator=torch.Generator().manual_seed(0)))
    assert palettes.permutation(5000) is palettes.permutation(5000)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_sh_palette_rows_are_channel_major(degree: int) -> None:
    """The palette's k-means sees each Gaussian's coefficients above the DC term channel by channel (R's, then G's,
    then B's: f_rest's order), as numpy's transposition puts them; its labels are the label texels' two bytes."""
    rng = np.random.default_rng(degree)
    sh = rng.normal(0, 0.05, (3000, (degree + 1) ** 2, 3)).astype(np.float32)
    rest = np.ascontiguousarray(sh[:, 1:].transpose(0, 2, 1).reshape(3000, -1))
    _, labels = palettes.kmeans(rest, 1024)
    _, _, _, texels = sog_texels.sh_palette(sh, degree, 1024, torch.device("cpu"))
    assert labels.max() >= 256  # both bytes in use
    np.testing.assert_array_equal(texels[:, 0] + 256 * texels[:, 1].astype(np.int64), labels)


def reference_pack_quats(quats: np.ndarray) -> np.ndarray:
    """The quaternion texels row by row (the writer's earlier numpy version): normalised by the float32 row norm,
    negated when the largest |component| (np.argmax: the first of equals) is negative, the other three as
    rint(255 (sqrt(2) c / 2 + 1/2)) clipped, A = 252 + the largest's index."""
    q = quats.astype(np.float64) / np.linalg.norm(quats, axis=1, keepdims=True)
    largest = np.abs(q).argmax(1)
    q *= np.where(np.take_along_axis(q, largest[:, None], 1) < 0, -1.0, 1.0) * math.sqrt(2.0)
    others = np.array([[j for j in range(4) if j != i] for i in range(4)])[largest]
    out = np.empty((len(q), 4), np.uint8)
    out[:, :3] = np.clip(np.rint(255.0 * (np.take_along_axis(q, others, 1) * 0.5 + 0.5)), 0, 255)
    out[:, 3] = 252 + largest
    return out


def test_quaternion_texels_match_a_row_by_row_version() -> None:
    rng = np.random.default_rng(8)
    q = rng.normal(size=(5000, 4))
    q[:400] = rng.choice([-0.5, 0.5], (400, 4))  # four equal magnitudes
    q[400:800] = rng.choice([-1.0, 0.0, 1.0], (400, 4))  # two or three equal, zeros
    q[800:1200] = np.round(q[800:1200] * 4) / 4  # components near rounding half-steps
    q[np.abs(q).sum(1) == 0] = [1.0, 0.0, 0.0, 0.0]
    q = (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)
    np.testing.assert_array_equal(sog_texels.pack_quats(torch.from_numpy(q)).numpy(), reference_pack_quats(q))


def test_writer_bytes_do_not_depend_on_threads() -> None:
    """The same bytes from the shared pool and torch's threads as from one pool thread and one torch thread."""
    scene = random_scene(np.random.default_rng(9), 3000, 2)
    usual = encode_sog(scene)
    pool, threads = row_tasks._pool, torch.get_num_threads()
    try:
        row_tasks._pool = ThreadPoolExecutor(1)
        torch.set_num_threads(1)
        assert encode_sog(scene) == usual
    finally:
        row_tasks._pool.shutdown()
        row_tasks._pool = pool
        torch.set_num_threads(threads)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (the texels quantised on a GPU)")
def test_texels_on_the_gpu_are_those_on_the_cpu() -> None:
    """Every texel and codebook entry the same on both devices (module docstring of ``sog_texels``: only a
    logarithm within an ulp of a boundary could differ, which these scenes do not hold), and the box within an
    ulp, on random scenes and on the bench scene."""
    from scenesplat_stereo.bench.scenes import synthetic_scene

    scenes = [random_scene(np.random.default_rng(s), 4000 + 999 * s, 0) for s in range(4)]
    for scene in [*scenes, synthetic_scene(202752, 0)]:
        texels, *box = sog_texels.placed(scene, torch.device("cpu"))
        texels_gpu, *box_gpu = sog_texels.placed(scene, torch.device("cuda"))
        np.testing.assert_array_equal(texels, texels_gpu)
        np.testing.assert_array_almost_equal_nulp(np.array(box), np.array(box_gpu), 1)
        for fn in (sog_texels.scale_texels, sog_texels.colour_texels):
            for cpu, gpu in zip(fn(scene, torch.device("cpu")), fn(scene, torch.device("cuda"))):
                np.testing.assert_array_equal(cpu, gpu)


@pytest.mark.parametrize("sizes", [[5, 0, 70000], [1], []])
def test_stored_zip_is_zipfiles_stored_zip(sizes: list[int]) -> None:
    """``stored_zip``'s bytes are those of ``zipfile``'s stored members dated 1980-01-01 (the writer's before
    it streamed its members), and ``zipfile`` reads them back with their CRCs checked; empty members, one, none."""
    import io
    import zlib

    from scenesplat_stereo.scene.sog import stored_zip

    rng = np.random.default_rng(0)
    members = [(f"m{i}.webp", rng.integers(0, 256, n, dtype=np.uint8).tobytes()) for i, n in enumerate(sizes)]
    members.append(("meta.json", json.dumps({"version": 2}).encode()))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as z:
        for name, data in members:
            z.writestr(zipfile.ZipInfo(name, (1980, 1, 1, 0, 0, 0)), data)
    ours = b"".join(stored_zip((name, data, zlib.crc32(data)) for name, data in members))
    assert ours == buf.getvalue()
    with zipfile.ZipFile(io.BytesIO(ours)) as z:
        assert z.testzip() is None and [(i.filename, z.read(i)) for i in z.infolist()] == members


def test_a_failed_encode_leaves_the_sog_there_as_it_was(tmp_path: Path, monkeypatch) -> None:
    """``save_sog`` writes the zip's members as their encodes end; an encode that fails after others were written
    leaves the file that was there untouched, and no temporary file."""
    from scenesplat_stereo.scene import sog

    scene = random_scene(np.random.default_rng(1), 500, 0)
    path = save_sog(scene, tmp_path / "s.sog")
    before = path.read_bytes()
    write_webp, calls = sog.write_webp, []

    def failing(rgba, width, height, method=sog.WEBP_METHOD):
        calls.append(1)
        if len(calls) == 4:
            raise sog.SogError("OpenImageIO cannot write WebP: the disk is full (a test)")
        return write_webp(rgba, width, height, method)

    monkeypatch.setattr(sog, "write_webp", failing)
    with pytest.raises(sog.SogError, match="a test"):
        save_sog(random_scene(np.random.default_rng(2), 700, 0), path)
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["s.sog"]


def test_a_scene_a_sog_cannot_hold_is_refused_before_any_file(tmp_path: Path) -> None:
    """The quantisation refuses it before ``save_sog`` opens a file: not even the folder is made."""
    from scenesplat_stereo.scene.sog import SogError

    with pytest.raises(SogError, match="an empty scene has no SOG"):
        save_sog(random_scene(np.random.default_rng(0), 0, 0), tmp_path / "new" / "s.sog")
    assert not (tmp_path / "new").exists()
