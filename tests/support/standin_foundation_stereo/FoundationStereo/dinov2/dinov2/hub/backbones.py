"""Stand-in for DINOv2's ``dinov2/hub/backbones.py``: with ``pretrained=True`` (the default, as in the real
one) the weights are downloaded, which an offline build must never ask for."""

import torch

from dinov2.models.vision_transformer import DinoVisionTransformer

WEIGHTS_URL = "https://weights.invalid/dinov2_{}14_pretrain.pth"


def _make(arch: str, embed_dim: int, pretrained: bool) -> DinoVisionTransformer:
    model = DinoVisionTransformer(embed_dim)
    if pretrained:
        model.load_state_dict(torch.hub.load_state_dict_from_url(WEIGHTS_URL.format(arch)))
    return model


def dinov2_vits14(*, pretrained: bool = True, **kwargs):
    return _make("vits", 8, pretrained)


def dinov2_vitl14(*, pretrained: bool = True, **kwargs):
    return _make("vitl", 16, pretrained)
