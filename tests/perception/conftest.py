"""Shared fixtures: small synthetic recordings (made once per session) and the PhysTwin-layout fixture."""

import shutil
from pathlib import Path

import pytest

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="session")
def phystwin_dir() -> Path:
    """The committed read-only PhysTwin raw-layout fixture (2 cameras, 3 frames, 64x48)."""
    return DATA / "phystwin_tiny"


@pytest.fixture
def phystwin_copy(tmp_path, phystwin_dir) -> Path:
    """A writable copy of the PhysTwin fixture, for corrupting."""
    dst = tmp_path / "rec"
    shutil.copytree(phystwin_dir, dst)
    return dst


@pytest.fixture(scope="session")
def rope_rec(tmp_path_factory) -> Path:
    """Rope: 10 frames at 10 fps (hold, lift, hold, release, settle), 3 cameras at 320x240."""
    from empm_gym.perception.synth import synthesize

    return synthesize(tmp_path_factory.mktemp("synth") / "rope", "rope", seed=1, frames=10, fps=10.0, cameras=3,
                      width=320, height=240, progress=False)


@pytest.fixture(scope="session")
def dough_rec(tmp_path_factory) -> Path:
    """Dough: 3 frames at 30 fps (hold, squeeze), 3 cameras at the full 848x480."""
    from empm_gym.perception.synth import synthesize

    return synthesize(tmp_path_factory.mktemp("synth") / "dough", "dough", seed=2, frames=3, cameras=3,
                      progress=False)
