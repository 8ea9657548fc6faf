"""Scene writers with faults, for ``sgmodel predict --video --frames``' writer processes
(``sgmodel.predict.scene_writers``): module-level, so a writer process can import them by name."""

from __future__ import annotations

import time
from pathlib import Path

from sgmodel.predict.scene_writers import write_scene

#: The frame whose write fails.
FAILING_FRAME = "000003"
#: The file a slow write leaves beside its scene once it has started.
STARTED = "writing-started"


def value_error_write(scene, path: Path, format: str) -> Path:
    """Frame ``FAILING_FRAME`` is bad input (ValueError: exit 2)."""
    if path.name.startswith(FAILING_FRAME):
        raise ValueError(f"{path.name}: broken on purpose")
    return write_scene(scene, path, format)


def runtime_error_write(scene, path: Path, format: str) -> Path:
    """Frame ``FAILING_FRAME`` hits a bug (RuntimeError: exit 1)."""
    if path.name.startswith(FAILING_FRAME):
        raise RuntimeError(f"{path.name}: broken on purpose")
    return write_scene(scene, path, format)


def slow_write(scene, path: Path, format: str) -> Path:
    """Leaves ``STARTED`` beside the scene, then writes it 0.2 s later."""
    (path.parent / STARTED).touch()
    time.sleep(0.2)
    return write_scene(scene, path, format)
