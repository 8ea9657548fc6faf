"""Stand-in for the ``hubconf.py`` of the DINOv2 copy FoundationStereo vendors in ``dinov2/``."""

from dinov2.hub.backbones import dinov2_vitl14, dinov2_vits14  # noqa: F401 - torch.hub entry points

dependencies = ["torch"]
