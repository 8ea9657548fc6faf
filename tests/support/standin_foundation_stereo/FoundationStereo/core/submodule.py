"""Stand-in for FoundationStereo's ``core/submodule.py``."""

from tests.support.standin_foundation_stereo.standin_stereo import Conv2xUp as Conv2x_IN  # noqa: F401 - used by core/extractor.py
