"""Where tests find things: the repository, the small test data it ships and the shared real data beside it."""

from __future__ import annotations

import os
from pathlib import Path

#: the repository root
REPO = Path(__file__).resolve().parents[2]
#: small inputs shipped with the tests (tests/data/README.md says how each was made)
TEST_DATA = REPO / "tests" / "data"
#: ``<repo>/../shared/data``: teachers and other real data shared by the team (read-only; may be absent)
SHARED_DATA = REPO.parent / "shared" / "data"
#: the real captures as published (SOG, .splat), ../shared/data/PROVENANCE.md
CAPTURES = SHARED_DATA / "captures"
#: streamed SOG scenes (lod-meta.json + chunk folders) fetched by hand: $STREAMED_SCENES or ../shared/data/streamed
STREAMED = Path(os.environ.get("STREAMED_SCENES", SHARED_DATA / "streamed"))
#: the npm package the scene files are checked against (``npm ci`` in scripts/checks/viewer)
SPLAT_TRANSFORM = (REPO / "scripts" / "checks" / "viewer" / "node_modules" / "@playcanvas" / "splat-transform" / "bin"
                   / "cli.mjs")
