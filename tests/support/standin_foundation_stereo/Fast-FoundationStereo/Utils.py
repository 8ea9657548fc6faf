"""Stand-in for NVlabs/Fast-FoundationStereo's top-level ``Utils.py`` (see ../README.md): ``AMP_DTYPE``, which
its ``core/`` imports (FoundationStereo's ``Utils.py`` has none)."""

import torch

AMP_DTYPE = torch.float16
