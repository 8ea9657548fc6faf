"""``sgmodel bench train``: the decoder + predictor's FLOP count against an analytical count of their
convolutions, the random-weight LPIPS it times, the optimiser it and ``sgmodel train`` share, and a tiny
run on the CPU that reports both loss terms."""

from __future__ import annotations

import torch

from sgmodel.bench.train import layer_flops, synthetic_batch
from sgmodel.cli import main as sgmodel_main
from sgmodel.config import DecoderParams, ModelParams, PredictorParams
from sgmodel.metrics.lpips import CHANNELS, random_lpips
from sgmodel.model.network import create_model
from sgmodel.train.step import create_optimizer
from tests.support.model_helpers import StandInEncoder


def conv_flops(batch: int, h: int, w: int, cin: int, cout: int, k: int, replicate: bool = False) -> int:
    """2 B H W Cout Cin k^2, plus the four one-pixel ring convolutions (kernel 3) of a replicate-padded one."""
    flops = 2 * batch * h * w * cout * cin * k * k
    return flops + (12 * batch * cout * cin * (h + w) if replicate else 0)


def test_layer_flops_match_an_analytical_count():
    S, P, C, Cp, B = 32, 2, 16, 8, 2
    params = ModelParams(resolution=S, padding=P, decoder=DecoderParams(channels=C, groups=4),
                         predictor=PredictorParams(channels=Cp, groups=4))
    model = create_model(params, encoder=StandInEncoder())
    batch = synthetic_batch(B, 2, S)
    expected = 0
    for cin, s in zip((6 + 4, 8 + 4), (2, 4)):  # the stand-in's feature maps with RGB-D: projection, 4 RCU convs
        expected += conv_flops(B, S // s, S // s, cin, C, 1) + 4 * conv_flops(B, S // s, S // s, C, C, 3)
    expected += conv_flops(B, S, S, C, C, 3) + conv_flops(B, S, S, C, C, 1)  # the head
    Hc = S + 2 * P
    expected += conv_flops(B, Hc, Hc, 4 + C, Cp, 3, True) + conv_flops(B, Hc, Hc, Cp, Cp, 3, True)  # regressor
    expected += conv_flops(B, Hc, Hc, Cp + 3 + C, 3 * Cp, 3, True)  # the branches' first layers as one
    expected += sum(conv_flops(B, Hc, Hc, Cp, cout, 3, True) for cout in (37, 37, 1))
    forward, total = layer_flops(model, batch, amp=False)
    assert forward == expected
    # backward: input and weight gradients (2x forward) less the inputs' gradients of the first convolutions
    # (the features need none), plus the ring terms recomputed in the replicate convolutions' backward
    assert 2.5 * forward < total < 3.1 * forward


def test_random_lpips_is_seeded_and_timing_only(tmp_path):
    a, b = random_lpips(seed=3), random_lpips(seed=3)
    assert a.vgg_sha256 == "random"
    for (ka, va), (kb, vb) in zip(a.state_dict().items(), b.state_dict().items()):
        assert ka == kb and torch.equal(va, vb)
    assert not torch.equal(random_lpips(seed=4).vgg.features[0].weight, a.vgg.features[0].weight)
    x = torch.rand(2, 3, 32, 32)
    assert [t.shape[1] for t in a.taps(x)] == list(CHANNELS)


def test_create_optimizer_is_adamw_with_the_settings():
    p = torch.nn.Parameter(torch.ones(3))
    opt = create_optimizer([p], torch.device("cpu"), lr=0.5, betas=(0.8, 0.9), weight_decay=0.1)
    assert isinstance(opt, torch.optim.AdamW)
    group = opt.param_groups[0]
    assert (group["lr"], group["betas"], group["weight_decay"]) == (0.5, (0.8, 0.9), 0.1) and not group["fused"]


def test_bench_train_reports_both_terms_on_the_cpu(tmp_path, capsys):
    out = tmp_path / "bench.md"
    rc = sgmodel_main(["bench", "train", "--device", "cpu", "--encoder", "sgbm", "--resolution", "16", "--padding", "2",
                       "--decoder-channels", "8", "--predictor-channels", "8", "--batch-size", "1", "--targets", "1",
                       "--warmup", "0", "--repeats", "1", "--lpips-random-vgg", "--no-amp", "--out", str(out)])
    assert rc == 0
    text = out.read_text()
    assert "| stage | mse+ssim, median ms | mse+lpips-vgg, median ms |" in text
    assert "**free-running step**" in text and "**back-to-back steps**" in text and "peak memory, MiB" in text
    assert "| first step, s (cuDNN's algorithm search; compilation) |" in text
    assert "the LPIPS term's VGG16 eager" in text  # compiled only on CUDA
    assert "| forward (the stage above) |" in text and "| forward + backward, alone |" in text
    assert text in capsys.readouterr().out
