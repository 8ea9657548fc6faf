"""Helpers of the bad-input suite (tests/test_bad_input_*.py): run a command, and prove that a refused
command left every existing file exactly as it was."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from scenesplat_stereo.scene.gaussians import GaussianScene, save_ply


def snapshot(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` (relative path -> bytes); {} when root does not exist."""
    root = Path(root)
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()} \
        if root.is_dir() else {}


def run_cli(main, argv: list[str], capsys) -> tuple[int, str]:
    """(exit status, stdout + stderr) of ``main(argv)``; argparse's SystemExit gives its code."""
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code if isinstance(e.code, int) else 1
    out = capsys.readouterr()
    return rc, out.out + out.err


def tiny_teacher(folder: Path, n_frames: int = 3, psnr: float = 33.0, size=(32, 24)) -> Path:
    """A plain-layout teacher: 50 Gaussians in front of the cameras, an OpenCV transforms.json, scene.json."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    n = 50
    quats = np.zeros((n, 4), np.float32)
    quats[:, 0] = 1
    means = (rng.normal(size=(n, 3)) * 0.3 + [0, 0, 3]).astype(np.float32)
    save_ply(GaussianScene(means, quats, np.full((n, 3), 0.05, np.float32), np.full(n, 0.8, np.float32),
                           rng.normal(size=(n, 1, 3)).astype(np.float32) * 0.3, 0), folder / "point_cloud.ply")
    w, h = size
    frames = []
    for i in range(n_frames):
        m = np.eye(4)
        m[0, 3] = 0.05 * i
        frames.append({"file_path": f"f{i}", "transform_matrix": m.tolist()})
    (folder / "transforms.json").write_text(json.dumps({"camera_convention": "opencv", "fl_x": 30.0, "fl_y": 30.0,
                                                        "w": w, "h": h, "frames": frames}))
    (folder / "scene.json").write_text(json.dumps({"psnr": psnr, "subset": "DemoGS"}))
    return folder


def snapshots(*folders: Path) -> list[dict[str, bytes]]:
    """``snapshot`` of each folder (for asserting that a refused command changed none of them)."""
    return [snapshot(f) for f in folders]


def refusal(main, argv: list, capsys) -> tuple[int, str]:
    """(exit status, stderr without Warp's CPU-only notice) of ``main(argv)``."""
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as e:
        rc = e.code if isinstance(e.code, int) else 1
    err = capsys.readouterr().err
    return rc, "\n".join(line for line in err.splitlines() if not line.startswith("Warp "))


def refused(main, argv: list, capsys, message: str, *folders: Path) -> None:
    """``main(argv)`` exits 2 with one line holding ``message`` and leaves every file under ``folders`` as it was."""
    before = snapshots(*folders)
    rc, err = refusal(main, argv, capsys)
    assert rc == 2 and len(err.splitlines()) == 1 and message in err, err
    assert snapshots(*folders) == before


def earlier_output(folder: Path, owner: str, names=("scene.ply",), user_file: str | None = "notes.txt") -> Path:
    """An earlier output of ``owner`` (its manifest lists ``names``), and a file of the user's added to it since."""
    from scenesplat_stereo.common.ownership import StagedFolder

    with StagedFolder(folder, owner) as tmp:
        for name in names:
            (tmp / name).parent.mkdir(parents=True, exist_ok=True)
            (tmp / name).write_text(f"an earlier {name}")
    if user_file:
        (folder / user_file).write_text("the user's own notes, added to the earlier output")
    return folder


def earlier_file(path: Path, owner: str, text: str = "an earlier report\n") -> Path:
    """An earlier single-file output of ``owner``: ``text`` at ``path``, its manifest (``.written-by.<name>``)
    beside it, as the command writes them (``scenesplat_stereo.common.ownership.write_owned_file``)."""
    from scenesplat_stereo.common.ownership import write_owned_file

    return write_owned_file(path, text.encode(), owner)


def model_checkpoint(path: Path, params=None, nan: bool = False, **fields) -> Path:
    """A checkpoint of an untrained model (``sgmodel.model.checkpoint`` format) of ``params`` (default: the
    cpu-small preset at 32x32, padding 2); ``nan`` puts a NaN in one weight; ``fields`` override the
    checkpoint's fields (e.g. ``format``)."""
    import torch

    from sgmodel.config import PRESETS, ModelParams
    from sgmodel.model.checkpoint import save_checkpoint
    from sgmodel.model.network import create_model

    if params is None:
        params = ModelParams.from_dict(PRESETS["cpu-small"]["model"])
        params.resolution, params.padding = 32, 2
    torch.manual_seed(0)
    state = create_model(params).state_dict()
    if nan:
        name = next(iter(state))
        state[name] = state[name].clone()
        state[name].view(-1)[0] = float("nan")
    save_checkpoint(path, {"model_params": params.to_dict(), "model": state, "step": 2, "encoder": {"name": "sgbm"},
                           **fields})
    return path
