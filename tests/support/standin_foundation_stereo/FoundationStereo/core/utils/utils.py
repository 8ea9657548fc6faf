"""Stand-in for FoundationStereo's ``core/utils/utils.py`` (``core/`` and ``core/utils/`` have no ``__init__.py``,
as in the real repository)."""

from tests.support.standin_foundation_stereo.standin_stereo import block_match, normalise  # noqa: F401 - used by core/
