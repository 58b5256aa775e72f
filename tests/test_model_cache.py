"""Outfit models kept on disk between runs (services.model_cache, services.cloth_job.build_outfit)."""

import logging
import shutil
from dataclasses import fields, is_dataclass

import numpy as np
import pytest

import services.cloth_job as cloth_job
from cloth.surface import SurfaceSettings
from services.cloth_job import OUTFITS, build_outfit, collision_body
from services.model_cache import ModelCache, cache_folder
from skinning.animate import BodyAnimator

LEVEL = 3


def assert_same(a, b, where="models"):
    """Every array, number and string of two object graphs equal (arrays bit for bit)."""
    assert type(a) is type(b), where
    if isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, where
        np.testing.assert_array_equal(a, b, err_msg=where)
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for k, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{where}[{k}]")
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            assert_same(a[k], b[k], f"{where}[{k!r}]")
    elif is_dataclass(a) or hasattr(a, "__dict__"):
        names = [f.name for f in fields(a)] if is_dataclass(a) else list(vars(a))
        for n in names:
            assert_same(getattr(a, n), getattr(b, n), f"{where}.{n}")
    else:
        assert a == b or (a != a and b != b), where  # (NaN equals NaN here)


@pytest.fixture(scope="module")
def rig(body):
    return BodyAnimator(body), collision_body(body)


def test_outfit_models_are_read_back_as_built_and_not_built_again(body, data, rig, tmp_path, monkeypatch):
    animator, mesh = rig
    outfit_dir = data / "garments" / OUTFITS[1]
    surface = SurfaceSettings(level=LEVEL)
    cache = ModelCache(tmp_path)
    built = build_outfit(body, animator, mesh, outfit_dir, surface=surface, cache=cache)
    assert (cache.builds, cache.hits) == (1, 0) and len(list((tmp_path / "models").glob("*.pickle"))) == 1
    assert built[1] is not None and len(built[1]) == 2 and len(built[2]) == 1  # two surfaces, one layer pair

    def no_build(*args, **kwargs):
        raise AssertionError("built again")

    monkeypatch.setattr(cloth_job, "load_outfit_models", no_build)
    again = ModelCache(tmp_path)  # (another run: a new cache object on the same folder)
    read = build_outfit(body, animator, mesh, outfit_dir, surface=surface, cache=again)
    assert (again.builds, again.hits) == (0, 1)
    assert read[0] is not built[0]
    assert_same(read, built)


def test_other_inputs_make_other_keys(body, data, rig, tmp_path):
    animator, mesh = rig
    cache = ModelCache(tmp_path / "cache")
    outfit_dir = tmp_path / OUTFITS[1]
    shutil.copytree(data / "garments" / OUTFITS[1], outfit_dir)
    build_outfit(body, animator, mesh, outfit_dir, surface=SurfaceSettings(level=LEVEL), cache=cache)
    build_outfit(body, animator, mesh, outfit_dir, surface=SurfaceSettings(level=LEVEL), cache=cache)
    assert (cache.builds, cache.hits) == (1, 1)
    build_outfit(body, animator, mesh, outfit_dir, surface=SurfaceSettings(level=LEVEL + 1), cache=cache)
    build_outfit(body, animator, mesh, outfit_dir, surface=None, cache=cache)
    assert (cache.builds, cache.hits) == (3, 1)
    # one garment file changed by a byte (a comment line): built again, not read
    mhclo = sorted(outfit_dir.rglob("*.mhclo"))[0]
    mhclo.write_text(mhclo.read_text(encoding="utf-8") + "\n# changed\n", encoding="utf-8")
    build_outfit(body, animator, mesh, outfit_dir, surface=SurfaceSettings(level=LEVEL), cache=cache)
    assert (cache.builds, cache.hits) == (4, 1)
    assert len(list((tmp_path / "cache" / "models").glob("*.pickle"))) == 4


def test_an_unreadable_file_is_built_again_and_replaced(body, data, rig, tmp_path, caplog):
    animator, mesh = rig
    outfit_dir = data / "garments" / OUTFITS[2]
    cache = ModelCache(tmp_path)
    built = build_outfit(body, animator, mesh, outfit_dir, cache=cache)  # coarse models only
    (path,) = (tmp_path / "models").glob("*.pickle")
    path.write_bytes(path.read_bytes()[:1000])  # cut short (a full disk, a killed writer of old)
    with caplog.at_level(logging.WARNING, logger="tryon.cache"):
        again = build_outfit(body, animator, mesh, outfit_dir, cache=cache)
    assert cache.builds == 2 and "cannot be read back" in caplog.text and path.name in caplog.text
    assert_same(again, built)
    third = ModelCache(tmp_path)
    build_outfit(body, animator, mesh, outfit_dir, cache=third)  # the file was replaced whole
    assert (third.builds, third.hits) == (0, 1)
    assert not list(tmp_path.rglob("*.part"))


def test_no_cache_when_off_or_unwritable(body, data, rig, tmp_path, caplog, monkeypatch):
    animator, mesh = rig
    assert cache_folder("off") is None and cache_folder(tmp_path) == tmp_path
    monkeypatch.setenv("TRYON_CACHE", "off")
    assert ModelCache.from_env().folder is None
    monkeypatch.setenv("TRYON_CACHE", str(tmp_path / "elsewhere"))
    assert ModelCache.from_env().folder == tmp_path / "elsewhere" / "models"
    blocked = tmp_path / "a-file"
    blocked.write_text("not a folder")
    cache = ModelCache(blocked)
    with caplog.at_level(logging.WARNING, logger="tryon.cache"):
        outfit, surfaces, layers = build_outfit(body, animator, mesh, data / "garments" / OUTFITS[2], cache=cache)
    assert cache.builds == 1 and "cannot write" in caplog.text
    assert len(outfit.models) == 2 and surfaces is None and layers == []
