"""Both command lines refuse abbreviated flags (allow_abbrev=False at every level): a shortened or mistyped
flag is an error naming it, never a silent match of a longer flag (``--rig`` was once taken for ``--right``)."""

from __future__ import annotations

import pytest

from pipelines import irs_targets
from scenesplat_stereo.cli import main as scenesplat_main
from sgmodel.cli import main as sgmodel_main


@pytest.mark.parametrize("main, argv, flag", [
    (sgmodel_main, ["predict", "--left", "l.png", "--right", "r.png", "--cal", "K.txt", "--out", "o",
                    "--method", "naive-gs"], "--cal"),
    (sgmodel_main, ["predict", "--left", "l.png", "--right", "r.png", "--out", "o", "--meth", "naive-gs"], "--meth"),
    (sgmodel_main, ["train", "--data", "d", "--out", "o", "--step", "3"], "--step"),
    (sgmodel_main, ["eval", "--data", "d", "--out", "o", "--method", "naive-gs", "--res", "64"], "--res"),
    (sgmodel_main, ["bench", "predict", "--rep", "2"], "--rep"),
    (scenesplat_main, ["build", "--teachers", "t", "--out", "o", "--val-scene", "1"], "--val-scene"),
    (scenesplat_main, ["demo-teachers", "o", "--scene", "2"], "--scene"),
    (irs_targets.main, ["poses", "--out", "o", "--min-tr", "1"], "--min-tr"),
])
def test_abbreviated_flag_is_refused(main, argv, flag, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    assert f"unrecognized arguments: {flag}" in capsys.readouterr().err


def test_full_flag_still_parses():
    from sgmodel.cli import build_parser

    args = build_parser().parse_args(["predict", "--left", "l.png", "--right", "r.png", "--out", "o",
                                      "--method", "naive-gs"])
    assert args.right == "r.png"
