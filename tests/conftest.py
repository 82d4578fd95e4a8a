import os

os.environ.setdefault("WARP_LOG_LEVEL", "error")

import pytest


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory):
    """The `tiny` synthetic capture, built once per test session (read-only for tests)."""
    from physavatar.synth import PRESETS, synthesize

    return synthesize(tmp_path_factory.mktemp("tiny_session") / "tiny", PRESETS["tiny"], progress=False)
