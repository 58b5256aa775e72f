import os
from pathlib import Path

import pytest

from skinning.data import data_dir

CLIPS = ["cmu_13_29_jumping_jacks", "cmu_131_01_walk_3dsmax", "cmu_npybvh_example_75f"]

# no second process compiling the surface's kernels ahead (services.warmup) in the commands the tests
# start: it would compete with the tests for the cores (its own tests set it back)
os.environ.setdefault("TRYON_WARMUP", "0")


@pytest.fixture(scope="session", autouse=True)
def model_cache(tmp_path_factory):
    """Outfit models built once for the whole run (services.model_cache), in a folder of the run's
    own rather than the user's cache; subprocesses started by the tests inherit it."""
    from services.model_cache import CACHE_ENV

    folder = tmp_path_factory.mktemp("model-cache")
    before = os.environ.get(CACHE_ENV)
    os.environ[CACHE_ENV] = str(folder)
    yield folder
    if before is None:
        os.environ.pop(CACHE_ENV, None)
    else:
        os.environ[CACHE_ENV] = before


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
