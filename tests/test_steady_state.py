"""A frame of the cloth pipeline in steady state allocates no arrays (the standards: hot paths over
preallocated arrays, no per-frame allocation)."""

import tracemalloc

from cloth.surface import SurfaceSettings
from services.cloth_job import OutfitSession, build_outfit, collision_body
from skinning.animate import BodyAnimator
from skinning.source import BVHSource

# bytes: what a frame may allocate at its peak, Python's own small objects (the frame's lists and tuples,
# the helper thread's handshake). A coarse garment's (n, 3) float64 array is 7.7 kB, a detailed surface's
# (N,) one 88 kB: one made per frame anywhere in S101-S106 or the layering goes over
PEAK_BYTES = 6_000


def test_a_frame_in_steady_state_allocates_no_arrays(body, data, mocap):
    with BVHSource(mocap / "cmu_131_01_walk_3dsmax.bvh", every=2, max_frames=60) as source:
        animator = BodyAnimator(body, source.skeleton)
        poses = [animator(f.local_rot, f.root_position).vertices.copy() for f in source]
    body_mesh = collision_body(body)
    outfit, surface_models, layers = build_outfit(body, animator, body_mesh, data / "garments" / "female_casualsuit01",
                                                  surface=SurfaceSettings())
    # two threads: the helper's garment too; a frame without the surface (a catching-up service's) too
    session = OutfitSession(body, animator, body_mesh, outfit, surface_models=surface_models, threads=2,
                            layers=layers)
    try:
        for v in poses[:30]:  # (the first frames size what they keep: the helper thread, the garments' order)
            session.step_cloth(v, 1 / 60)
        tracemalloc.start()
        try:
            before = tracemalloc.get_traced_memory()[0]
            for k, v in enumerate(poses[30:]):
                session.step_cloth(v, 1 / 60, surface=k % 10 != 9)
            now, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
    finally:
        session.close()
    assert peak - before < PEAK_BYTES, f"a frame allocated {peak - before} bytes at its peak"
    assert now - before < PEAK_BYTES  # and keeps nothing
