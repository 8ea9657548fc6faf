"""Where tests find things: the repository, the small test data it ships and the shared real data beside it."""

from __future__ import annotations

from pathlib import Path

#: the repository root
REPO = Path(__file__).resolve().parents[2]
#: small inputs shipped with the tests (tests/data/README.md says how each was made)
TEST_DATA = REPO / "tests" / "data"
#: ``<repo>/../shared/data``: teachers and other real data shared by the team (read-only; may be absent)
SHARED_DATA = REPO.parent / "shared" / "data"
