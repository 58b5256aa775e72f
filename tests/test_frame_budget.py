"""A session's level of detail: the governor that holds a frame budget, the wrinkles carried from
one tessellation level to another, and a session going on at another level."""

from __future__ import annotations

import numpy as np
import pytest

from cloth.pn import resample_heights
from cloth.surface import DetailedSurface
from services.frame_budget import LOWEST_LEVEL, LevelGovernor
from tests.test_surface import DT, compressed_strip, run_frames, sheet_model

# ---------------------------------------------------------------- the governor


def feed(g: LevelGovernor, seconds: float, frames: int) -> list[int]:
    """The levels asked for over `frames` frames of `seconds` each, each change made at once."""
    asked = []
    for _ in range(frames):
        want = g.observe(seconds)
        if want is not None:
            asked.append(want)
            g.changed(want)
    return asked


def test_a_session_over_its_budget_goes_down_a_window_at_a_time_to_the_lowest():
    g = LevelGovernor(0.008, 6, window=30)
    assert [g.observe(0.010) for _ in range(29)] == [None] * 29  # not before a whole window
    assert g.observe(0.010) == 5
    g.changed(5)
    assert feed(g, 0.010, 200) == [4, 3]  # one level per window, never below the lowest
    assert g.level == LOWEST_LEVEL and g.changes == 3
    # far over: down as far as the vertex ratio says at once, 6 (8 / 32)^0.5 = 3
    g = LevelGovernor(0.008, 6, window=30)
    assert feed(g, 0.032, 30) == [3]
    g = LevelGovernor(0.008, 8, window=30)
    assert feed(g, 0.018, 30) == [5]  # 8 (8 / 18)^0.5 = 5.3


def test_the_slow_tail_decides_not_the_median():
    """The 90th percentile: 2 slow frames in 30 keep the level, 4 lower it."""
    for slow, asked in ((2, None), (4, 5)):
        g = LevelGovernor(0.008, 6, window=30)
        times = [0.005] * (30 - slow) + [0.009] * slow
        answers = [g.observe(t) for t in times]
        assert answers[:-1] == [None] * 29 and answers[-1] == asked


def test_a_session_with_room_goes_back_up_to_its_asked_level_and_no_further():
    g = LevelGovernor(0.008, 6, window=30, rise_frames=120)
    g.changed(4)
    # 4 ms at level 4: level 5 is expected at 4 (5/4)² = 6.25 ms, within 0.8 of the budget (6.4)
    asked = []
    for frame in range(119):
        assert g.observe(0.004) is None, frame  # not before rise_frames at this level
    asked.append(g.observe(0.004))
    assert asked == [5]
    g.changed(5)
    # 4 ms at level 5: level 6 is expected at 5.76 ms: up again after another 120 frames, then no further
    assert feed(g, 0.004, 500) == [6]


def test_no_rise_where_the_next_level_would_not_fit():
    g = LevelGovernor(0.008, 6, window=30, rise_frames=30)
    g.changed(5)
    assert feed(g, 0.0046, 600) == []  # level 6 expected at 6.6 ms, over 0.8 of the budget


def test_a_rise_taken_back_doubles_the_wait_before_the_next():
    g = LevelGovernor(0.008, 6, window=30, rise_frames=60)
    g.changed(5)
    assert feed(g, 0.004, 60) == [6]
    assert feed(g, 0.010, 30) == [5]  # level 6 was too slow after all
    assert feed(g, 0.004, 60) == []  # waits 120 frames now
    assert feed(g, 0.004, 60) == [6]


@pytest.mark.parametrize("kwargs", [dict(budget=0.0, top=6), dict(budget=float("nan"), top=6),
                                    dict(budget=0.008, top=0), dict(budget=0.008, top=6, window=0),
                                    dict(budget=0.008, top=6, window=30, rise_frames=10)])
def test_governor_settings_out_of_range_are_refused(kwargs):
    with pytest.raises(ValueError):
        LevelGovernor(**kwargs)


# ---------------------------------------------------------------- wrinkles carried between levels


@pytest.mark.parametrize("src, dst", [(6, 4), (4, 6), (6, 3), (5, 7)])
def test_heights_linear_over_the_coarse_faces_carry_to_another_level_exactly(src, dst):
    """Heights interpolated linearly from values at the coarse vertices (continuous across the
    coarse faces) are the same function at every level: resampled, they are reproduced exactly."""
    a, b = sheet_model(level=src).tess, sheet_model(level=dst).tess
    g = np.random.default_rng(7).uniform(-0.01, 0.02, a.n_coarse)

    def linear(t):
        corners = t.coarse_triangles[t.owner_face]
        return (t.owner_weights * g[corners]).sum(axis=1)

    out = np.full(b.n_vertices, np.nan)
    resample_heights(a.face_ids, a.level, b.owner_face, b.owner_weights, linear(a), out)
    np.testing.assert_allclose(out, linear(b), atol=1e-15)


def test_heights_at_the_points_both_lattices_share_carry_unchanged():
    """Level 6 to 3: every level-3 particle is a level-6 particle; any heights there come over as they are."""
    a, b = sheet_model(level=6).tess, sheet_model(level=3).tess
    h = np.random.default_rng(3).uniform(0.0, 0.01, a.n_vertices)
    out = np.zeros(b.n_vertices)
    resample_heights(a.face_ids, a.level, b.owner_face, b.owner_weights, h, out)
    for f in range(len(b.coarse_triangles)):
        for k, (bb, cc) in enumerate(b.lattice):
            kk = [i for i, (b6, c6) in enumerate(a.lattice) if b6 == 2 * bb and c6 == 2 * cc][0]
            assert out[b.face_ids[f, k]] == h[a.face_ids[f, kk]]
    assert out.min() >= h.min() and out.max() <= h.max()


def test_wrinkles_carried_to_another_level_stay_where_they_were():
    """A compressed strip's wrinkles at level 6, carried to level 4: the new surface starts with
    them (the heights along the coarse edges the same where the levels share points), and steps on
    as a level-4 surface that grew them itself would: its arc lengths back near rest."""
    m6, x = compressed_strip(0.8)
    surf6 = DetailedSurface(m6)
    run_frames(surf6, x, 120)
    assert surf6.state.dh.max() > 0.003
    m4 = sheet_model(nx=5, nz=3, level=4)
    surf4 = DetailedSurface(m4)
    surf4.state.body_face[:] = 7  # (what a surface used before holds: the carry starts it afresh)
    surf4.carry_heights_from(surf6)
    assert np.all(surf4.state.body_face == -1)
    # the coarse vertices and the edges' midpoints are particles of both
    t6, t4 = m6.tess, m4.tess
    np.testing.assert_array_equal(surf4.state.dh[:t4.n_coarse], surf6.state.dh[:t6.n_coarse])
    np.testing.assert_array_equal(surf4.state.dh[t4.edge_ids[:, 2]], surf6.state.dh[t6.edge_ids[:, 3]])
    p, _ = run_frames(surf4, x, 30)
    ratio = np.linalg.norm(np.diff(p[t4.edge_ids], axis=1), axis=2).sum(axis=1) / m4.edge_rest
    assert abs(np.median(ratio) - 1.0) < 0.05
    with pytest.raises(ValueError, match="not over the same coarse triangles"):
        DetailedSurface(sheet_model(nx=4, nz=3, level=4)).carry_heights_from(surf6)


# ---------------------------------------------------------------- a session at another level


def test_an_outfit_session_goes_on_at_another_level_and_back(body, data):
    """The casual outfit stepped at level 4, then at level 3 (the coarse cloth going on as it
    was, the wrinkles carried), then back at level 4 on the surfaces it had: a snapshot taken
    there before the change restores onto them and the frames after it come out bit for bit."""
    from cloth.surface import SurfaceSettings
    from services.cloth_job import START_FRAME, OutfitSession, build_outfit, collision_body
    from services.model_cache import ModelCache
    from skinning.animate import BodyAnimator
    from skinning.source import BVHSource

    with BVHSource(data / "mocap" / "cmu_npybvh_example_75f.bvh", every=2, max_frames=START_FRAME + 9) as source:
        animator = BodyAnimator(body, source.skeleton)
        poses = [animator(f.local_rot, f.root_position).retarget.q.copy() for f in source if f.index >= START_FRAME]
    frames = [animator.pose(q).vertices.copy() for q in poses]
    mesh = collision_body(body)
    outfit_dir, cache = data / "garments" / "female_casualsuit01", ModelCache.from_env()
    outfit, s4, layers4 = build_outfit(body, animator, mesh, outfit_dir, surface=SurfaceSettings(level=4), cache=cache)
    _, s3, layers3 = build_outfit(body, animator, mesh, outfit_dir, surface=SurfaceSettings(level=3), cache=cache)
    sim = OutfitSession(body, animator, mesh, outfit, surface_models=s4, layers=layers4, threads=1)
    try:
        sim.preroll(poses[0], DT)
        for v in frames[:4]:
            sim.step_cloth(v, DT)
        start = sim.snapshot()
        p4 = [sim.detailed[k][0].copy() for k in range(2)]
        sim.step_cloth(frames[4], DT)
        after4 = [sim.detailed[k][0].copy() for k in range(2)]
        coarse4 = [s.state.x.copy() for s in sim.sims]
        start.restore()
        sim.change_level(s3, layers3)
        assert sim.level == 3
        old = sim._by_level[4][0]
        for k in range(2):  # the coarse vertices' heights carried as they were (points of both levels)
            n = s3[k].tess.n_coarse
            np.testing.assert_array_equal(sim.surfaces[k].state.dh[:n], old[k].state.dh[:n])
        assert max(np.abs(sf.state.dh).max() for sf in sim.surfaces) > 0.0
        sim.step_cloth(frames[4], DT)
        for k in range(2):
            p, n = sim.detailed[k]
            assert p.shape == (s3[k].n_vertices, 3) and np.isfinite(p).all() and np.isfinite(n).all()
            # the coarse cloth stepped on as it would have at level 4
            np.testing.assert_array_equal(sim.sims[k].state.x, coarse4[k])
        for v in frames[5:8]:
            sim.step_cloth(v, DT)
        # back to level 4: the same surface objects; the snapshot of before the change puts it all back
        sim.change_level(s4, layers4)
        assert sim.level == 4 and all(a is b for a, b in zip(sim.surfaces, old))
        start.restore()
        for k in range(2):
            np.testing.assert_array_equal(sim.surfaces[k].state.p, p4[k])
        sim.step_cloth(frames[4], DT)
        for k in range(2):
            np.testing.assert_array_equal(sim.detailed[k][0], after4[k])
    finally:
        sim.close()


@pytest.mark.parametrize("command", [["cloth-service"], ["session"]])
@pytest.mark.parametrize("value", ["0", "-2", "nan", "fast"])
def test_a_frame_budget_that_is_not_a_positive_number_is_refused_naming_it(command, value, capsys):
    from services.cli import main

    with pytest.raises(SystemExit):
        main([*command, "--frame-budget-ms", value])
    shown = repr(value) if value == "fast" else value  # (what float() could not read, quoted)
    assert f"argument --frame-budget-ms: must be a number of milliseconds > 0, got {shown}" in capsys.readouterr().err
