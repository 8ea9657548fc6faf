"""Stand-in for NVlabs/FoundationStereo's top-level ``Utils.py`` (see ../README.md): the helpers its ``core/``
imports. Like the real one it has no ``AMP_DTYPE`` (Fast-FoundationStereo's ``Utils.py`` has)."""

import math


def freeze_model(model):
    """Eval mode, no gradients."""
    model = model.eval()
    for p in model.parameters():
        p.requires_grad = False
    return model


def get_resize_keep_aspect_ratio(H, W, divider=16, max_H=1232, max_W=1232):
    """(H', W'): H and W rounded up to multiples of ``divider``, scaled down to fit max_H x max_W."""
    h, w = math.ceil(H / divider) * divider, math.ceil(W / divider) * divider
    scale = min(1.0, max_H / h, max_W / w)
    return math.ceil(h * scale / divider) * divider, math.ceil(w * scale / divider) * divider
