"""Stand-in for Fast-FoundationStereo's ``core/utils/utils.py``."""

from tests.support.standin_foundation_stereo.standin_stereo import block_match, correlation, normalise  # noqa: F401 - used by core/
