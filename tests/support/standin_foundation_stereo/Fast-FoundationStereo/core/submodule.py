"""Stand-in for Fast-FoundationStereo's ``core/submodule.py``: it imports ``AMP_DTYPE`` from the top-level
``Utils`` (the name that collides with FoundationStereo's ``Utils.py``)."""

import Utils as U  # noqa: F401 - as in the real module
from Utils import AMP_DTYPE  # noqa: F401

from tests.support.standin_foundation_stereo.standin_stereo import Conv2xUp as Conv2x_IN  # noqa: F401 - used by core/extractor.py
