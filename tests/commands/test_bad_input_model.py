"""Bad input to ``sgmodel train``, ``eval``, ``predict``, ``ablate`` and ``weights``: exit 2, one line naming the
flag, or the file and the field, and every folder that was there before (an earlier run, report, prediction
or ablation, the dataset, the inputs) byte-for-byte unchanged (docs/bad_input.md lists the cases)."""

from __future__ import annotations

import json
import re
import shutil
import tarfile
from pathlib import Path

import cv2
import numpy as np
import OpenImageIO as oiio
import pytest

from scenesplat_stereo.common import ownership
from scenesplat_stereo.common.ownership import FolderLock, StagedFolder
from scenesplat_stereo.shards.encode import decode_image, encode_png
from sgmodel.cli import main
from sgmodel.config import PRESETS, ModelParams
from tests.support.bad_input import model_checkpoint, refusal, snapshots


def matches(message: str, err: str) -> bool:
    """``message`` is in ``err``; a message with ``.*`` or a backslash is a regular expression."""
    return bool(re.search(message, err)) if ".*" in message or "\\" in message else message in err


TINY = ["--preset", "cpu-small", "--resolution", "32", "--padding", "2", "--steps", "2", "--val-every", "2",
        "--device", "cpu", "--no-progress"]


@pytest.fixture
def earlier_run(tmp_path) -> Path:
    """A run folder of an earlier training (its files must survive every refused command)."""
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"model": {}, "train": {}, "data": "elsewhere", "encoder": {},
                                                 "loss": {}, "init_from": None}))
    (run / "checkpoints" / "last.pt").write_bytes(b"an earlier checkpoint")
    (run / "metrics.jsonl").write_text('{"step": 0, "val_psnr": 20.0}\n')
    return run


@pytest.fixture(scope="module")
def broken_data(demo_dataset, tmp_path_factory) -> dict[str, Path]:
    """Copies of the demo dataset, each damaged one way."""
    root = tmp_path_factory.mktemp("broken")
    out = {}
    for name in ("no_val", "bad_index", "truncated_shard", "shard_not_tar"):
        out[name] = shutil.copytree(demo_dataset, root / name)
    shutil.rmtree(out["no_val"] / "val")
    (out["bad_index"] / "train" / "index.json").write_text('{"shards": [')
    shard = out["truncated_shard"] / "train" / "shard-000000.tar"
    shard.write_bytes(shard.read_bytes()[:30000])
    (out["shard_not_tar"] / "train" / "shard-000000.tar").write_bytes(b"not a tar" * 100)
    (root / "empty").mkdir()
    out["empty"] = root / "empty"
    (root / "a_file").write_text("not a dataset")
    out["a_file"] = root / "a_file"
    return out


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory) -> dict[str, Path]:
    """Checkpoints of untrained cpu-small models at 32x32: good, diverged (a NaN), another format version,
    model_params of another version, another architecture, and not a checkpoint at all."""
    root = tmp_path_factory.mktemp("ckpts")
    wide = ModelParams.from_dict(PRESETS["cpu-small"]["model"])
    wide.resolution, wide.padding, wide.decoder.channels, wide.predictor.channels = 32, 2, 64, 64
    out = {"good": model_checkpoint(root / "good.pt"), "nan": model_checkpoint(root / "nan.pt", nan=True),
           "old": model_checkpoint(root / "old.pt", format="sgmodel-checkpoint-v0"),
           "wide": model_checkpoint(root / "wide.pt", wide)}
    newer = model_checkpoint(root / "newer.pt")
    import torch

    ckpt = torch.load(newer, weights_only=True)
    ckpt["model_params"]["tiling"] = "future"
    torch.save(ckpt, newer)
    out["newer"] = newer
    (root / "junk.pt").write_bytes(b"\x00garbage" * 50)
    out["junk"] = root / "junk.pt"
    return out


# ------------------------------------------------------------------------------------------------ train

TRAIN_FLAGS = [  # (flags, message); each refused by its argparse type or the parameter check, before anything
    (["--lr", "0"], "--lr 0.0: must be > 0"),
    (["--lr", "-0.001"], "--lr -0.001: must be > 0"),
    (["--lr", "nan"], "--lr 'nan': expected a finite number"),
    (["--lpips-weight", "-1"], "--lpips-weight -1.0: must be >= 0"),
    (["--lpips-weight", "inf"], "--lpips-weight 'inf': expected a finite number"),
    (["--weight-decay", "-0.1"], "--weight-decay -0.1: must be >= 0"),
    (["--weight-decay", "nan"], "--weight-decay 'nan': expected a finite number"),
    (["--warmup", "1"], "--warmup 1.0: must be < 1.0"),
    (["--warmup", "0"], "--warmup 0.0: must be > 0.0"),
    (["--seed", "-1"], "--seed -1: must be >= 0"),
    (["--seed", "1.5"], "--seed '1.5': expected a whole number"),
    (["--resolution", "30"], "--resolution 30: must be a multiple of 16 and >= 16"),
    (["--resolution", "8"], "--resolution 8: must be >= 16"),
    (["--padding", "-1"], "--padding -1: must be >= 0"),
    (["--decoder-channels", "12"], "--decoder-channels 12: must be a positive multiple of decoder.groups (8)"),
    (["--edge-mask", "hard", "--no-back-layer"], "--edge-mask hard: an edge mask gates the back layer"),
    (["--steps", "0"], "--steps 0: must be >= 1"),
    (["--batch-size", "0"], "--batch-size 0: must be >= 1"),
    (["--accumulate", "0"], "--accumulate 0: must be >= 1"),
    (["--accumulate", "3"], r"--accumulate 3: must divide the batch per rank \(4 = --batch-size 4 over 1 rank"),
    (["--val-samples", "0"], "--val-samples 0: must be >= 1"),
    (["--device", "tpu"], "--device 'tpu': expected cpu, cuda or cuda:<n>"),
    (["--device", "mps"], "--device 'mps': the rasteriser runs on cpu or cuda only"),
    (["--device", "cuda:7"], "--device cuda:7: no CUDA device is available to torch"),
    (["--encoder", "nope"], "--encoder nope: unknown encoder; available: "),
    (["--encoder-weights", "/nonexistent/w.pth"], "--encoder-weights: encoder 'sgbm' is classical and takes no "
                                                   "weights"),
    (["--targets", "11"], "--targets: .*shard-000000.tar:.*field 'targets': 10 stored, 11 asked for"),
    (["--lpips-vgg", "/nonexistent/vgg16.pth"], "--lpips-vgg /nonexistent/vgg16.pth: no such file"),
]


@pytest.mark.parametrize("flags,message", TRAIN_FLAGS, ids=[" ".join(c[0]) for c in TRAIN_FLAGS])
def test_train_refuses_before_writing(demo_dataset, earlier_run, capsys, flags, message):
    before = snapshots(earlier_run, demo_dataset)
    rc, err = refusal(main, ["train", "--data", demo_dataset, "--out", earlier_run, *TINY, *flags], capsys)
    assert rc == 2 and len(err.splitlines()) == 1 and err.startswith("sgmodel train: error: "), err
    assert matches(message, err), err
    assert snapshots(earlier_run, demo_dataset) == before


DATA_CASES = [
    ("missing", "nothing-here: data folder does not exist"),
    ("a_file", "a_file: not a folder"),
    ("empty", r"empty/train: split 'train' does not exist \(splits here: none\)"),
    ("no_val", r"no_val/val: split 'val' does not exist \(splits here: \['train'\]\)"),
    ("bad_index", r"bad_index/train/index.json: malformed"),
    ("truncated_shard", r"truncated_shard/train/shard-000000.tar: member '.*': truncated or corrupt tar"),
    ("shard_not_tar", r"shard_not_tar/train/shard-000000.tar: its first member: truncated or corrupt tar"),
]


@pytest.mark.parametrize("case,message", DATA_CASES, ids=[c[0] for c in DATA_CASES])
def test_train_names_the_broken_data_file(broken_data, tmp_path, capsys, case, message):
    data = broken_data.get(case, tmp_path / "nothing-here")
    before = snapshots(data)
    rc, err = refusal(main, ["train", "--data", data, "--out", tmp_path / "run", *TINY], capsys)
    assert rc == 2 and len(err.splitlines()) == 1 and matches(message, err), err
    assert not (tmp_path / "run").exists() and snapshots(data) == before


def test_train_out_is_a_file(demo_dataset, tmp_path, capsys):
    out = tmp_path / "run.txt"
    out.write_text("notes")
    rc, err = refusal(main, ["train", "--data", demo_dataset, "--out", out, *TINY], capsys)
    assert rc == 2 and f"--out {out}: exists and is not a folder" in err and out.read_text() == "notes"


def test_train_out_under_a_file(demo_dataset, tmp_path, capsys):
    (tmp_path / "notes").write_text("x")
    rc, err = refusal(main, ["train", "--data", demo_dataset, "--out", tmp_path / "notes" / "run", *TINY], capsys)
    assert rc == 2 and "cannot be created" in err and "notes is a file" in err
    assert (tmp_path / "notes").read_text() == "x"


def test_train_out_inside_the_dataset(demo_dataset, capsys):
    before = snapshots(demo_dataset)
    rc, err = refusal(main, ["train", "--data", demo_dataset, "--out", demo_dataset / "runs" / "a", *TINY], capsys)
    assert rc == 2 and "inside --data" in err and snapshots(demo_dataset) == before


def test_train_out_not_writable(demo_dataset, tmp_path, capsys, monkeypatch):
    def denied(*a, **k):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(ownership.tempfile, "mkstemp", denied)  # the root user cannot be refused by chmod
    rc, err = refusal(main, ["train", "--data", demo_dataset, "--out", tmp_path / "run", *TINY], capsys)
    assert rc == 2 and "--out" in err and "not writable" in err and "Permission denied" in err
    assert not (tmp_path / "run").exists()


def test_train_out_holds_other_files(demo_dataset, tmp_path, capsys):
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "a.jpg").write_bytes(b"jpeg")
    before = snapshots(tmp_path / "photos")
    rc, err = refusal(main, ["train", "--data", demo_dataset, "--out", tmp_path / "photos", *TINY], capsys)
    assert rc == 2 and "holds files not written by `sgmodel train` (e.g. 'a.jpg')" in err
    assert snapshots(tmp_path / "photos") == before


def test_train_out_holds_a_run_of_other_settings(demo_dataset, earlier_run, capsys):
    before = snapshots(earlier_run)
    rc, err = refusal(main, ["train", "--data", demo_dataset, "--out", earlier_run, *TINY], capsys)
    assert rc == 2 and "holds a run trained with other settings (model, data, encoder, loss, train differ)" in err
    assert f"--init-from {earlier_run / 'checkpoints' / 'last.pt'}" in err and snapshots(earlier_run) == before


def test_train_out_with_a_corrupt_config(demo_dataset, earlier_run, capsys):
    (earlier_run / "config.json").write_text('{"model": ')
    before = snapshots(earlier_run)
    rc, err = refusal(main, ["train", "--data", demo_dataset, "--out", earlier_run, *TINY], capsys)
    assert rc == 2 and "config.json: not valid JSON (line 1, column 11" in err and snapshots(earlier_run) == before


def test_train_out_locked_by_a_live_process(demo_dataset, tmp_path, capsys):
    with FolderLock(tmp_path / "run", "--out", "sgmodel train"):  # another process's lock, as far as flock goes
        before = snapshots(tmp_path / "run")
        rc, err = refusal(main, ["train", "--data", demo_dataset, "--out", tmp_path / "run", *TINY], capsys)
        assert rc == 2 and "another `sgmodel train` (pid" in err and "is writing it" in err
        assert snapshots(tmp_path / "run") == before


INIT_CASES = [
    ("missing", r"--init-from .*missing.pt: no such checkpoint file"),
    ("junk", r"--init-from .*junk.pt: not a readable PyTorch checkpoint"),
    ("nan", r"--init-from .*nan.pt: 1 weight tensors hold NaN or infinity .*a diverged model"),
    ("old", r"--init-from .*old.pt: format 'sgmodel-checkpoint-v0' \(another version of sgmodel\)"),
    ("wide", r"--init-from .*wide.pt: its weights do not fit this model \(size mismatch"),
]


@pytest.mark.parametrize("case,message", INIT_CASES, ids=[c[0] for c in INIT_CASES])
def test_train_init_from_is_checked(demo_dataset, checkpoints, tmp_path, capsys, case, message):
    ckpt = checkpoints.get(case, tmp_path / "missing.pt")
    before = snapshots(ckpt.parent)
    rc, err = refusal(main, ["train", "--data", demo_dataset, "--out", tmp_path / "run", *TINY, "--init-from", ckpt],
                      capsys)
    assert rc == 2 and len(err.splitlines()) == 1 and matches(message, err), err
    assert not (tmp_path / "run").exists() and snapshots(ckpt.parent) == before


# ------------------------------------------------------------------------------------------------- eval


@pytest.fixture
def earlier_report(tmp_path) -> Path:
    with StagedFolder(tmp_path / "report", "sgmodel eval") as tmp:
        (tmp / "metrics.json").write_text('{"earlier": true}\n')
    return tmp_path / "report"


EVAL_CASES = [
    (["--checkpoint", "{missing}"], "missing.pt: no such checkpoint file"),
    (["--checkpoint", "{junk}"], "junk.pt: not a readable PyTorch checkpoint"),
    (["--checkpoint", "{nan}"], "nan.pt: 1 weight tensors hold NaN or infinity"),
    (["--checkpoint", "{old}"], "old.pt: format 'sgmodel-checkpoint-v0' (another version of sgmodel)"),
    (["--checkpoint", "{newer}"], "newer.pt: its model_params do not fit this version of sgmodel"),
    (["--method", "naive-gs", "--encoder", "nope"], "--encoder nope: unknown encoder; available: "),
    (["--method", "naive-gs", "--split", "test"], "split 'test' does not exist"),
    (["--method", "naive-gs", "--batch-size", "0"], "--batch-size 0: must be >= 1"),
    (["--method", "naive-gs", "--resolution", "8"], "--resolution 8: must be >= 16"),
    (["--method", "naive-gs", "--device", "cuda:1"], "--device cuda:1: no CUDA device"),
]


@pytest.mark.parametrize("flags,message", EVAL_CASES, ids=[" ".join(c[0]) for c in EVAL_CASES])
def test_eval_refuses_before_writing(demo_dataset, checkpoints, earlier_report, tmp_path, capsys, flags, message):
    flags = [f.format(missing=tmp_path / "missing.pt", **checkpoints) for f in flags]
    before = snapshots(earlier_report, checkpoints["good"].parent)
    rc, err = refusal(main, ["eval", "--data", demo_dataset, "--out", earlier_report, "--encoder", "sgbm",
                             "--no-progress", "--device", "cpu", *flags], capsys)
    assert rc == 2 and len(err.splitlines()) == 1 and message in err, err
    assert snapshots(earlier_report, checkpoints["good"].parent) == before


def test_eval_out_of_other_files_is_not_replaced(demo_dataset, tmp_path, capsys):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.md").write_text("mine")
    rc, err = refusal(main, ["eval", "--data", demo_dataset, "--out", tmp_path / "mine", "--method", "naive-gs",
                             "--encoder", "sgbm", "--device", "cpu"], capsys)
    assert rc == 2 and "holds files not written by `sgmodel eval` (e.g. 'notes.md')" in err
    assert (tmp_path / "mine" / "notes.md").read_text() == "mine"


def test_eval_out_holding_the_checkpoint(demo_dataset, checkpoints, earlier_report, capsys):
    """REPORT is replaced as a whole: a checkpoint inside it would be deleted."""
    ckpt = shutil.copy(checkpoints["good"], earlier_report / "best.pt")
    before = snapshots(earlier_report)
    rc, err = refusal(main, ["eval", "--data", demo_dataset, "--out", earlier_report, "--checkpoint", ckpt,
                             "--device", "cpu"], capsys)
    assert rc == 2 and f"--out {earlier_report}: holds --checkpoint {ckpt}, and the whole folder is replaced" in err
    assert snapshots(earlier_report) == before


# ---------------------------------------------------------------------------------------------- predict


@pytest.fixture
def pair(tmp_path) -> Path:
    """A 48x32 textured stereo pair (the right image shifted 2 px), a FoundationStereo K.txt, and an
    earlier prediction in OUT."""
    rng = np.random.default_rng(0)
    img = cv2.resize((rng.random((8, 16, 3)) * 255).astype(np.uint8), (52, 32), interpolation=cv2.INTER_CUBIC)
    (tmp_path / "l.png").write_bytes(encode_png(img[:, 2:50]))
    (tmp_path / "r.png").write_bytes(encode_png(img[:, 4:52]))
    (tmp_path / "tiny.png").write_bytes(encode_png(img[:1, :1]))
    (tmp_path / "K.txt").write_text("50 0 24 0 50 16 0 0 1\n0.1\n")
    with StagedFolder(tmp_path / "out", "sgmodel predict") as tmp:
        (tmp / "scene.ply").write_text("an earlier scene")
    return tmp_path


PREDICT_CASES = [
    ({"--left": "tiny.png"}, "--left .*tiny.png: 1x1 pixels is too small for a stereo pair"),
    ({"--calib": "far.txt"}, r"far.txt: principal point cx=96, cy=64 lies outside .*l.png \(48x32 pixels\)"),
    ({"--calib": "neg.txt"}, r"neg.txt: principal point cx=-3"),
    ({"--calib": "mb_doffs.txt"}, r"mb_doffs.txt: 100.0% of the pixels get a depth at the clamp .* doffs -500 px"),
    ({"--checkpoint": "nan.pt", "--method": None}, r"nan.pt: 1 weight tensors hold NaN or infinity"),
    ({"--out": "l.png"}, r"--out .*l.png: inside --left .*l.png; write outputs apart from the inputs"),
    ({"--out": "."}, r"--out .*: holds --left .*l.png, and the whole folder is replaced"),
    ({"--device": "cuda:2"}, r"--device cuda:2: no CUDA device"),
]


@pytest.mark.parametrize("change,message", PREDICT_CASES, ids=[" ".join(f"{k} {v}" for k, v in c[0].items())
                                                               for c in PREDICT_CASES])
def test_predict_refuses_before_writing(pair, checkpoints, capsys, change, message):
    (pair / "far.txt").write_text("50 0 96 0 50 64 0 0 1\n0.1\n")  # K of a 96x64 image
    (pair / "neg.txt").write_text("50 0 -3 0 50 16 0 0 1\n0.1\n")
    (pair / "mb_doffs.txt").write_text("cam0=[50 0 24; 0 50 16; 0 0 1]\ncam1=[50 0 24; 0 50 16; 0 0 1]\n"
                                       "doffs=-500\nbaseline=100\nwidth=48\nheight=32\n")
    shutil.copy(checkpoints["nan"], pair / "nan.pt")
    args = {"--left": "l.png", "--right": "r.png", "--calib": "K.txt", "--method": "naive-gs", "--out": "out",
            "--device": "cpu", "--encoder": "sgbm", "--resolution": "32"}
    args.update(change)
    plain = ("--device", "--method", "--encoder", "--resolution")
    argv = [x for k, v in args.items() if v is not None for x in (k, v if k in plain else pair / v)]
    before = snapshots(pair)
    rc, err = refusal(main, ["predict", *argv], capsys)
    *warnings, last = err.splitlines()  # a doffs at the clamp also trips the stereo check's swapped-pair warning
    assert rc == 2 and last.startswith("sgmodel predict: error: ") and matches(message, last), err
    assert all(w.startswith("sgmodel predict: warning: ") for w in warnings), err
    assert snapshots(pair) == before


def test_predict_out_holding_an_input(pair, capsys):
    shutil.copy(pair / "l.png", pair / "out" / "l.png")
    before = snapshots(pair)
    rc, err = refusal(main, ["predict", "--left", pair / "out" / "l.png", "--right", pair / "r.png", "--calib",
                             pair / "K.txt", "--method", "naive-gs", "--encoder", "sgbm", "--device", "cpu", "--out",
                             pair / "out"], capsys)
    assert rc == 2 and f"holds --left {pair / 'out' / 'l.png'}, and the whole folder is replaced" in err, err
    assert snapshots(pair) == before


def test_predict_replaces_an_earlier_prediction_whole(pair, capsys):
    """An earlier naive-gs prediction's scene.ply must not stay beside a forward-splat one (which has none)."""
    common = ["predict", "--left", pair / "l.png", "--right", pair / "r.png", "--calib", pair / "K.txt", "--encoder",
              "sgbm", "--resolution", "32", "--device", "cpu", "--out", pair / "out"]
    assert (pair / "out" / "scene.ply").read_text() == "an earlier scene"
    rc, err = refusal(main, [*common, "--method", "naive-gs"], capsys)
    assert rc == 0, err
    assert (pair / "out" / "scene.ply").read_bytes().startswith(b"ply")
    rc, err = refusal(main, [*common, "--method", "forward-splat"], capsys)
    assert rc == 0, err
    assert not (pair / "out" / "scene.ply").exists() and (pair / "out" / "views" / "left.png").is_file()
    assert not [p for p in pair.iterdir() if p.name.startswith(".tmp-")]  # no staging folder left


def test_predict_warns_when_the_principal_point_is_far_from_the_centre(pair, capsys):
    (pair / "half.txt").write_text("25 0 12 0 25 8 0 0 1\n0.1\n")  # K of a 24x16 image: cx, cy at a quarter
    rc, err = refusal(main, ["predict", "--left", pair / "l.png", "--right", pair / "r.png", "--calib",
                             pair / "half.txt", "--method", "forward-splat", "--encoder", "sgbm", "--resolution",
                             "32", "--device", "cpu", "--out", pair / "out"], capsys)
    assert rc == 0, err
    assert "sgmodel predict: warning: " in err and "half.txt: principal point cx=12, cy=8 is 25% of the image" in err


@pytest.mark.parametrize("orientation", range(1, 9))
def test_exif_orientation_is_applied_as_opencv_does(tmp_path, orientation):
    """A JPEG whose EXIF Orientation tag says how to turn it upright decodes upright (OpenCV's imread, which
    applies the tag, is the reference)."""
    rng = np.random.default_rng(orientation)
    img = np.kron((rng.random((3, 5, 3)) * 255).astype(np.uint8), np.ones((16, 16, 1), np.uint8))
    path = str(tmp_path / "photo.jpg")
    spec = oiio.ImageSpec(80, 48, 3, "uint8")
    spec.attribute("Orientation", orientation)
    out = oiio.ImageOutput.create(path)
    assert out.open(path, spec) and out.write_image(img)
    out.close()
    ours = decode_image(Path(path).read_bytes(), "jpg")
    reference = cv2.imread(path)[:, :, ::-1]
    assert ours.shape == reference.shape == ((48, 80, 3) if orientation < 5 else (80, 48, 3))
    assert np.array_equal(ours, reference)


# ----------------------------------------------------------------------------------------------- ablate


@pytest.fixture
def earlier_ablation(tmp_path) -> Path:
    """An earlier ablation's OUT: its files, and its manifest listing them (``sgmodel ablate`` wrote them)."""
    out = tmp_path / "ablation"
    (out / "shared-default" / "eval").mkdir(parents=True)
    (out / "shared-default" / "eval" / "metrics.json").write_text('{"mean": {}}\n')
    (out / "table.md").write_text("| earlier |\n")
    ownership.write_manifest(out, "sgmodel ablate")
    return out


ABLATE_CASES = [
    (["--only", "descriptr"], "--only 'descriptr': matches no variant; the variants are Shared default, Without "
                              "descriptor"),
    (["--only", "default", "nothing-like-this"], "--only 'nothing-like-this': matches no variant"),
    (["--lr", "inf"], "--lr 'inf': expected a finite number"),
    (["--resolution", "40"], "--resolution 40: must be a multiple of 16"),
    (["--targets", "12"], "field 'targets': 10 stored, 12 asked for"),
]


@pytest.mark.parametrize("flags,message", ABLATE_CASES, ids=[" ".join(c[0]) for c in ABLATE_CASES])
def test_ablate_refuses_before_writing(demo_dataset, earlier_ablation, capsys, flags, message):
    before = snapshots(earlier_ablation)
    rc, err = refusal(main, ["ablate", "--data", demo_dataset, "--out", earlier_ablation, *TINY, *flags], capsys)
    assert rc == 2 and len(err.splitlines()) == 1 and message in err, err
    assert snapshots(earlier_ablation) == before


def test_ablate_out_of_other_files(demo_dataset, tmp_path, capsys):
    (tmp_path / "thesis").mkdir()
    (tmp_path / "thesis" / "main.tex").write_text("x")
    rc, err = refusal(main, ["ablate", "--data", demo_dataset, "--out", tmp_path / "thesis", *TINY], capsys)
    assert rc == 2 and "holds files not written by `sgmodel ablate` (e.g. 'main.tex')" in err
    assert [p.name for p in (tmp_path / "thesis").iterdir()] == ["main.tex"]


# ---------------------------------------------------------------------------------------------- weights


@pytest.mark.parametrize("argv,message", [
    (["weights", "fetch", "resnet"], "sgmodel weights fetch: error: argument names: invalid choice: 'resnet'"),
    (["weights"], "sgmodel weights: error: the following arguments are required: weights_command"),
    (["train", "--data"], "sgmodel train: error: argument --data: expected one argument"),
    (["eval", "--dat", "x"], "sgmodel eval: error: the following arguments are required"),
])
def test_argparse_refusals_are_one_line(capsys, argv, message):
    rc, err = refusal(main, argv, capsys)
    assert rc == 2 and err.startswith(message) and len(err.splitlines()) == 1, err


def test_truncated_shard_in_a_loader_worker_is_named(demo_dataset, tmp_path):
    """A shard cut short after the checks (the loader reads it in full) names the shard and the member."""
    from sgmodel.data.loader import make_loader

    data = shutil.copytree(demo_dataset, tmp_path / "data")
    shard = data / "val" / "shard-000001.tar"
    with tarfile.open(shard) as t:
        last = t.getmembers()[-1]
    shard.write_bytes(shard.read_bytes()[:last.offset_data + 10])
    with pytest.raises(ValueError, match=rf"shard-000001.tar: member '{last.name}': truncated or corrupt tar"):
        list(make_loader(data, "val", 2, 32, None, train=False))
