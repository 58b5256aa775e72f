import os
from pathlib import Path

import pytest

from skinning.data import data_dir

CLIPS = ["cmu_13_29_jumping_jacks", "cmu_131_01_walk_3dsmax", "cmu_npybvh_example_75f"]


@pytest.fixture(scope="session")
def data() -> Path:
    return data_dir()


@pytest.fixture(scope="session")
def body(data):
    from skinning.body import load_body

    return load_body(data)


@pytest.fixture(scope="session")
def mocap(data) -> Path:
    return data / "mocap"


@pytest.fixture(scope="session")
def cli_env() -> dict[str, str]:
    """The environment for a `python -m services.cli` subprocess: this checkout first on its path."""
    root = Path(__file__).resolve().parents[1]
    return dict(os.environ, PYTHONPATH=str(root) + os.pathsep + os.environ.get("PYTHONPATH", ""))
