"""Fixtures for the synthetic scene generator tests: small scenes, built once per session."""

from __future__ import annotations

import pytest

from neb_slam_core.synth import generate as gen


@pytest.fixture(scope="session")
def small_sequence():
    """The 'small' preset (one room) with 12 frames, no images rendered."""
    return gen.build_sequence(gen.resolve_spec("small", n_frames=12))


@pytest.fixture(scope="session")
def default_sequence():
    """The 'default' multi-room preset with its 300 poses, no images rendered."""
    return gen.build_sequence(gen.resolve_spec("default"))


@pytest.fixture(scope="session")
def small_folder(tmp_path_factory):
    """A written 'small' sequence: 5 frames at 64x48."""
    out = tmp_path_factory.mktemp("synth") / "small"
    gen.generate("small", out, n_frames=5, size=(64, 48), progress=False)
    return out
