"""A user's own body: a data folder whose `body/base.obj` is another MakeHuman body of the same
topology (hm08, as MakeHuman exports a character made with its modifiers), beside the shipped rig,
weights, garments and motion. The skeleton comes from the new mesh's joint cubes, the garments are
fitted on it by their .mhclo files, and the cloth keeps the same guarantees as on the shipped body."""

from pathlib import Path

import numpy as np
import pytest

from skinning.body import load_body
from tests.cloth_acceptance import measure

WIDER = 1.12  # the reshaped body: broader and deeper (x and z about its vertical axis) ...
TALLER = 1.05  # ... and taller (y from the floor)


def _reshaped_obj(src: Path, dst: Path) -> tuple[float, float]:
    """base.obj with every `v` line (skin, helpers and joint cubes alike) moved: x and z scaled
    by WIDER about the skin's vertical axis, y by TALLER from its lowest point. Returns that axis
    (x, z) in the file's units."""
    lines = src.read_text().split("\n")
    v = np.array([[float(t) for t in ln.split()[1:4]] for ln in lines if ln.startswith("v ")])
    cx, cz = (v[:, 0].max() + v[:, 0].min()) / 2, (v[:, 2].max() + v[:, 2].min()) / 2
    floor = v[:, 1].min()
    out, k = [], 0
    for ln in lines:
        if ln.startswith("v "):
            x, y, z = v[k]
            k += 1
            ln = f"v {cx + (x - cx) * WIDER:.6f} {floor + (y - floor) * TALLER:.6f} {cz + (z - cz) * WIDER:.6f}"
        out.append(ln)
    dst.write_text("\n".join(out))
    return cx, cz


@pytest.fixture(scope="module")
def own_data(data, tmp_path_factory) -> Path:
    """A data folder of its own: the shipped files linked, base.obj reshaped."""
    root = tmp_path_factory.mktemp("own-data")
    for name in ("garments", "mocap"):
        (root / name).symlink_to(data / name, target_is_directory=True)
    (root / "body").mkdir()
    for f in (data / "body").iterdir():
        if f.name != "base.obj":
            (root / "body" / f.name).symlink_to(f, target_is_directory=f.is_dir())
    _reshaped_obj(data / "body" / "base.obj", root / "body" / "base.obj")
    return root


@pytest.fixture(scope="module")
def own_body(own_data):
    return load_body(own_data)


def test_the_skeleton_and_skin_follow_the_users_body(body, own_body):
    """The joints are the new mesh's joint cubes: every bone head moves as the mesh does (a known
    affine map), and the skin keeps its topology and weights."""
    assert own_body.n_visible == body.n_visible
    # (each quad split along its shorter diagonal, which the new shape may change)
    assert own_body.triangles.shape == body.triangles.shape
    np.testing.assert_array_equal(own_body.weight_bones, body.weight_bones)
    skin, own = body.vertices[: body.n_visible], own_body.vertices[: body.n_visible]
    for axis, ratio in ((0, WIDER), (1, TALLER), (2, WIDER)):
        extent = np.ptp(own[:, axis]) / np.ptp(skin[:, axis])
        assert extent == pytest.approx(ratio, rel=1e-5), axis
    # the same affine map carries the shipped bone heads onto the new ones
    all_v, all_own = body.vertices, own_body.vertices
    scale = np.ptp(all_own, axis=0) / np.ptp(all_v, axis=0)
    mapped = (body.skeleton.heads - all_v.min(axis=0)) * scale + all_own.min(axis=0)
    np.testing.assert_allclose(own_body.skeleton.heads, mapped, atol=1e-5)
    floor = (body.floor_y - all_v[:, 1].min()) * TALLER + all_own[:, 1].min()
    assert own_body.floor_y == pytest.approx(floor, abs=1e-6)


def test_garments_fit_the_users_body_and_keep_the_cloths_guarantees(body, own_body, own_data):
    """The casual outfit through the run clip on the reshaped body: the garments are fitted on it
    (the jeans' rest width grows with the hips), and as on the shipped body no NaN, no coarse
    particle deeper than 1 mm (independent signed distance), the waistband within 3 cm of the
    skin, nothing thrown off the body."""
    from skinning.animate import BodyAnimator

    records, report = measure(own_body, own_data, "female_casualsuit01", "cmu_npybvh_example_75f")
    assert report.frames > 30
    # fitted on the reshaped body: the garments' particles lie on its rest skin as the shipped fit lies
    # on the shipped skin (median distance to the skin T-shirt 10, jeans 12 mm), and off the shipped
    # skin (31 and 24 mm)
    for body_, near in ((own_body, True), (body, False)):
        skin = (body_.vertices + BodyAnimator(body_, contact=None).world_offset)[: body_.n_visible]
        for m in report.models:
            gap = np.median([np.sqrt(((skin - x) ** 2).sum(axis=1).min()) for x in m.rest_positions])
            assert (gap < 0.02) == near, (m.name, near, gap)
    for r in records:
        assert r.nan_frames == 0, r.name
        assert r.deepest > -0.001, f"{r.name}: {r.deepest * 1000:.1f} mm deep"
        assert max(r.off_body) < 0.2, r.name
        if r.name.endswith(".bottom"):
            assert max(r.waist_gap) < 0.03, f"{r.name}: waistband {max(r.waist_gap) * 100:.1f} cm off"
