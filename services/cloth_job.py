"""The cloth job: an outfit on the retargeted, skinned body through a clip (S101 coarse cloth).

Session start: the garments are fitted on the rest body, then the body is blended from its
rest pose to the clip's first frame over a pre-roll, and held there to settle, so the clip
starts with the garments on and at rest.
"""

from __future__ import annotations

import logging

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pinocchio as pin

from cloth.coarse_layers import CoarseLayerModel, CoarseLayerState, carry_inner, same_depth_pairs
from cloth.collision import BodyMesh, BodyPose
from cloth.fabric import (OUTFIT_FABRICS, Fabric, FabricError, fabric as fabric_preset, fabric_choice,
                          garment_fabrics, outfit_fabrics)
from cloth.garment import Garment, load_garments, mix_terms, outfit_source, worn_from_waist
from cloth.geometry import vertex_normals as geometry_vertex_normals
from cloth.layers import LAYER_BAND, SPLIT_CANDIDATES, LayerModel, LayerState, layer_outfit, stack_layer
from cloth.model import ClothModel, SimSettings
from cloth.sim import ClothSim, prepare_cloth
from cloth.snapshot import StateSnapshot
from cloth.surface import DetailedSurface, SurfaceSettings, build_surface_model
from skinning.animate import BodyAnimator
from skinning.body import ARM_LIMBS, LEG_LIMBS, Body, body_clothed_faces, body_hand_faces, body_regions
from skinning.contact import ContactSettings
from skinning.retarget import IKSettings
from skinning.source import BVHSource

from .model_cache import ModelCache, folder_digest, object_digest
from .spin import SpinPool

log = logging.getLogger("tryon.cloth")

OUTFITS = ("female_casualsuit01", "female_elegantsuit01", "female_sportsuit01")
# Default fabric per garment (blouse: silk, skirt: cotton, T-shirt: cotton, jeans: denim, sportswear: jersey).
DEFAULT_FABRICS = {
    "female_elegantsuit01.top": "silk",
    "female_elegantsuit01.bottom": "cotton",
    "female_casualsuit01.top": "cotton",
    "female_casualsuit01.bottom": "denim",
    "female_sportsuit01.top": "jersey",
    "female_sportsuit01.bottom": "jersey",
}
GARMENT_COLORS = [(0.25, 0.42, 0.75), (0.78, 0.33, 0.28), (0.35, 0.6, 0.38), (0.65, 0.55, 0.25)]
# MB clips begin with the converter's T-pose, 10 cm below the floor: start from frame 1.
START_FRAME = 1


def find_outfit(data: Path, name: str | Path) -> Path:
    """An outfit: a path to a MakeHuman outfit folder, to a garment mesh file already placed on the
    rest body, or to a folder of such files, or the name of one in <data>/garments, or garments of
    those there mixed (`female_casualsuit01.top+female_elegantsuit01.bottom`, `cloth.garment.mix_terms`).
    FileNotFoundError naming where it looked and which outfits there are; GarmentError where what
    is there holds no outfit (`cloth.garment.outfit_source`)."""
    path = Path(name) if Path(name).exists() else Path(data) / "garments" / str(name)
    if not path.exists() and mix_terms(path) is None:
        there = sorted(p.name for p in (Path(data) / "garments").glob("*") if p.is_dir())
        raise FileNotFoundError(f"outfit {str(name)!r} not found (looked for {path}); available: {there}")
    outfit_source(path)
    return path


def outfit_checker(data: Path) -> Callable[[dict], None]:
    """`IngestService.check_outfit` for a data folder: a requested outfit must be there, and a
    fabric must be a preset, or garment=preset pairs (`fabric_choice`; each refusal names what is
    wrong and what there is)."""
    def check(change: dict) -> None:
        find_outfit(data, change["outfit"])
        if change.get("fabric") is not None:
            fabric_choice(change["fabric"])
    return check


# m: how far into the hand from the wrist the cloth's winding surface reaches (BodyMesh.build's wound_faces);
# None: the whole hand, fingers and thumb (Decision, sixty-sixth session: a skirt under the fingers)
WRIST_REACH: float | None = None


def collision_body(body: Body) -> BodyMesh:
    """The body as the cloth collides with it: its parts (upper arms and forearms apart, one
    sleeve over both; lower legs and feet apart, one trouser leg over both), the faces clothes
    can touch, numbered along a Morton curve; its winding number counts the hands too (WRIST_REACH:
    the whole hands; BodyMesh.build's wound_faces)."""
    clothed = body_clothed_faces(body)
    return BodyMesh.build(body.triangles, body.n_visible, body_regions(body), clothed, body.vertices,
                          limbs=ARM_LIMBS + LEG_LIMBS, wound_faces=clothed | body_hand_faces(body, WRIST_REACH))


def smoothstep(t: float) -> float:
    return t * t * (3.0 - 2.0 * t)


@dataclass
class Outfit:
    name: str
    garments: list[Garment]
    models: list[ClothModel]
    rest_body: np.ndarray  # the skinned rest body they were fitted on (world frame)
    # garments made to lie at the same depth (two tops), the later worn over the earlier (`cloth.coarse_layers`)
    over: list[CoarseLayerModel] = field(default_factory=list)


def outfit_layers(outfit: "Outfit", surface_models: list, n_visible: int) -> list[LayerModel]:
    """The outfit's layer pairs (`cloth.layers`): which garment is worn over which, from the
    garments' detailed surfaces and the body at rest (garments of the same depth: as their coarse
    cloths are, `Outfit.over`)."""
    return layer_outfit(surface_models, np.ascontiguousarray(outfit.rest_body[:n_visible], dtype=np.float64),
                        {(m.outer, m.inner) for m in outfit.over})


def load_outfit_models(body: Body, animator: BodyAnimator, body_mesh: BodyMesh, outfit_dir: Path,
                       fabrics: dict[str, Fabric] | Fabric | None = None,
                       settings: SimSettings | None = None) -> Outfit:
    """Fit an outfit on the rest body (world frame: floor at y = 0) and build each garment's coarse
    model. outfit_dir: a MakeHuman outfit folder, or garment meshes already on the rest body (a
    file or a folder of them; `find_outfit`). A garment worn from the waist (`worn_from_waist`:
    trousers, a skirt) is held up by its waistband (elastic or buttoned), which grips the body."""
    garments, rest_body, skin = outfit_garments(body, animator, outfit_dir)
    models = [prepare_cloth(g, fab, rest_body, body_mesh, settings, grip_waistband=worn_from_waist(g, skin))
              for g, fab in zip(garments, garment_fabric_list(outfit_dir, garments, fabrics))]
    over = same_depth_pairs([m.rest_positions for m in models], [m.triangles for m in models],
                            [m.fabric.thickness for m in models])
    return Outfit(outfit_name(outfit_dir), garments, models, rest_body, over)


def outfit_garments(body: Body, animator: BodyAnimator, outfit_dir: Path) -> tuple[list[Garment], np.ndarray,
                                                                                   np.ndarray]:
    """An outfit's garments on the rest body (world frame: floor at y = 0; `load_garments`), with the
    skinned rest body they lie on and its visible vertices (the skin)."""
    rest_body = animator.pose(animator.rest_configuration()).vertices.copy()
    skin = rest_body[: body.n_visible]
    return load_garments(outfit_dir, body.vertices + animator.world_offset, skin), rest_body, skin


def garment_fabric_list(outfit_dir: Path, garments: list[Garment],
                        fabrics: dict[str, Fabric] | Fabric | None = None) -> list[Fabric]:
    """Each garment's fabric: `fabrics` where it is one fabric for all; else the garment's in
    `fabrics` (a per-garment choice, `fabric_choice`: by name or the part after the outfit's),
    else the outfit folder's fabrics.toml's, else the shipped garment's default
    (DEFAULT_FABRICS), else cotton. FabricError naming a garment the choice or the file names that
    the outfit lacks."""
    if isinstance(fabrics, Fabric):
        return [fabrics] * len(garments)
    names = [g.name for g in garments]
    chosen = garment_fabrics(fabrics, names) if fabrics else {}
    made = {}
    terms = mix_terms(outfit_dir)
    if terms is not None:  # a mix: each garment's outfit's own fabrics
        for outfit, _ in terms:
            if (outfit / OUTFIT_FABRICS).is_file():
                made.update((n, f) for n, f in outfit_fabrics(outfit / OUTFIT_FABRICS).items() if n in names)
    elif (Path(outfit_dir) / OUTFIT_FABRICS).is_file():  # the outfit's own fabrics
        own = Path(outfit_dir) / OUTFIT_FABRICS
        made = outfit_fabrics(own)
        stray = sorted(set(made) - set(names))
        if stray:
            raise FabricError(f"{own}: [garments] names {stray}, which the outfit does not have; it has {names}")
    made.update(chosen)
    return [made[n] if n in made else fabric_preset(DEFAULT_FABRICS.get(n, "cotton")) for n in names]


def outfit_digest(path: Path) -> str:
    """A digest of an outfit's files (`folder_digest`), of each of a mix's outfits' with the mix's name."""
    terms = mix_terms(path)
    if terms is None:
        return folder_digest(path)
    return object_digest((Path(path).name, [folder_digest(outfit) for outfit, _ in terms]))


def outfit_name(path: Path) -> str:
    """An outfit's name: its folder's, or its garment file's without the suffix."""
    return Path(path).stem if Path(path).is_file() else Path(path).name


def build_outfit(body: Body, animator: BodyAnimator, body_mesh: BodyMesh, outfit_dir: Path,
                 fabrics: dict[str, Fabric] | Fabric | None = None, settings: SimSettings | None = None,
                 surface: SurfaceSettings | None = None, cache: ModelCache | None = None,
                 body_digest: str | None = None) -> tuple[Outfit, list | None, list[LayerModel]]:
    """An outfit's models: (the fitted outfit and its coarse models, the detailed surface models
    at `surface`'s settings or None, the layer pairs), read from `cache` when they were built
    before from the same body, outfit files, fabrics, settings and code (`services.model_cache`).
    body_digest: `object_digest(body)`, if the caller keeps it (else computed here)."""
    outfit_dir = Path(outfit_dir)

    def build():
        outfit = load_outfit_models(body, animator, body_mesh, outfit_dir, fabrics, settings)
        if surface is None:
            return outfit, None, []
        surfaces = [build_surface_model(m, surface) for m in outfit.models]
        return outfit, surfaces, outfit_layers(outfit, surfaces, body.n_visible)

    if cache is None or cache.folder is None:
        built = build()
    else:
        rest = animator.pose(animator.rest_configuration()).vertices  # what the garments are fitted on
        parts = ("outfit models", body_digest or object_digest(body), object_digest((rest, animator.world_offset)),
                 outfit_name(outfit_dir), outfit_digest(outfit_dir), fabrics, settings, surface)
        built = cache.get(parts, build)
    for m in built[0].over:
        names = [built[0].models[m.outer].name, built[0].models[m.inner].name]
        log.info("outfit %s: %s is worn over %s, named before it (the two lie at the same depth: %.0f %% and %.0f %% "
                 "of them within %.0f mm of the other at rest)", outfit_name(outfit_dir), *names,
                 *(100 * o for o in m.overlap), LAYER_BAND * 1000)
    return built


@dataclass
class ClothReport:
    clip: str
    outfit: str
    garments: list[str]
    frames: int = 0
    substeps: list[int] = field(default_factory=list)
    stage_ms: dict[str, list[float]] = field(default_factory=dict)  # per garment-frame: whole S101 step
    split_ms: dict[str, list[tuple[float, float]]] = field(default_factory=dict)  # (integration, collision), profile
    surface_ms: dict[str, list[tuple[float, float, float]]] = field(default_factory=dict)  # PN, collision, deformation
    layer_ms: list[float] = field(default_factory=list)  # per frame: the outfit's layering (cloth.layers), all pairs
    nan_frames: int = 0
    resets: list[int] = field(default_factory=list)  # particles reset per garment
    snapshots: list[tuple[int, np.ndarray, list[np.ndarray]]] = field(default_factory=list)
    detailed_snapshots: list[list[tuple[np.ndarray, np.ndarray]]] = field(default_factory=list)  # per snapshot
    surface_triangles: list[np.ndarray] = field(default_factory=list)  # per garment, detailed mesh
    models: list[ClothModel] = field(default_factory=list)

    def summary(self) -> str:
        ms = "  ".join(f"{k} {np.median(v):.3f}" for k, v in self.stage_ms.items())
        if self.surface_ms:
            ms += " | surface PN/collision/deformation: " + "  ".join(
                f"{k} " + "/".join(f"{x:.2f}" for x in np.median(np.array(v), axis=0))
                for k, v in self.surface_ms.items())
        if self.layer_ms:
            ms += f" | layering {np.median(self.layer_ms):.2f}"
        made = ", ".join(f"{m.name} {m.fabric.name}" for m in self.models)
        return (f"{self.clip} × {self.outfit} ({made}): {self.frames} frames, substeps {self.substeps} | "
                f"median ms per garment-frame: {ms} | NaN frames {self.nan_frames} | resets {self.resets}")


class OutfitSession:
    """Body animator + one ClothSim per garment; `step_cloth()` advances everything by one frame."""

    PREROLL_SURFACE_STEPS = 10

    def __init__(self, body: Body, animator: BodyAnimator, body_mesh: BodyMesh, outfit: Outfit,
                 surface: SurfaceSettings | None = None, surface_models: list | None = None,
                 threads: int | None = None, pool: SpinPool | None = None,
                 layers: list[LayerModel] | None = None):
        """surface: also build each garment's detailed surface (S102-S106) at these settings;
        surface_models: the garments' surface models, already built (shared between sessions);
        threads: garments stepped in parallel (default: one per garment, at most one per core):
        the calling thread steps its share and helper threads the rest;
        pool: the helper threads, shared with other sessions (`services.spin.SpinPool`; a frame
        that finds them busy is stepped on the calling thread alone); default: its own;
        layers: the outfit's layer pairs (`cloth.layers`, shared between sessions; default: found
        from the surface models, `outfit_layers`), whose outer detailed surfaces are kept over the
        inner ones (and the inner ones under the outer) after every garment has stepped."""
        self.body, self.animator, self.outfit, self.body_mesh = body, animator, outfit, body_mesh
        self.sims = [ClothSim(m, body_mesh, outfit.rest_body) for m in outfit.models]
        # garments worn over others of the same depth: the outer's coarse cloth kept over the inner's
        self.over = [(m, CoarseLayerState(m, outfit.models[m.inner].n_particles)) for m in outfit.over]
        for m, s in self.over:
            self.sims[m.outer].worn_over.append((m, s))
        if surface_models is None and surface is not None:
            surface_models = [build_surface_model(m, surface) for m in outfit.models]
        self.surfaces = [DetailedSurface(sm) for sm in surface_models or []]
        if layers is None:
            layers = outfit_layers(outfit, surface_models, body.n_visible) if surface_models else []
        self.layers = [(lm, LayerState(lm)) for lm in layers]
        self._by_level: dict = {}  # the surfaces of the other levels this session used (`change_level`)
        self._split_layers = any(max(len(lm.over.candidates), len(lm.under.candidates)) >= SPLIT_CANDIDATES
                                 for lm in layers)
        # handed to on_garment only once layered (the outer lifted, the inner pressed)
        self.layered_garments = {lm.outer for lm in layers} | {lm.inner for lm in layers}
        self.layer_seconds = 0.0
        self._detailed: list = [None] * len(self.sims)
        self._frame = None
        threads = min(len(self.sims), os.cpu_count() or 1) if threads is None else threads
        threads = max(1, min(threads, len(self.sims)))
        self._own_pool = pool is None and threads > 1
        self._pool = SpinPool(threads - 1, 0.0) if self._own_pool else pool
        self._threads = threads
        # each garment's step time, a running average (s): with n threads, the garments in order of
        # it go to threads 0, 1, .., n - 1, 0, ..: the caller (thread 0), which also updates the
        # body's queries (0.7 ms), takes the cheapest (the elegant outfit's skirt, not its blouse:
        # 0.5 ms off the frame, offline). Which thread steps a garment never changes its result.
        self.garment_seconds = np.zeros(len(self.sims))
        self._order = list(range(len(self.sims)))
        self._shares = self._share_out(self._order)
        self.detailed: list[tuple[np.ndarray, np.ndarray]] = []  # per garment: (positions, normals) of the last frame
        self.surface_seconds = np.zeros((len(self.sims), 3))
        # the frame's body: face normals, vertex grid, face tree; shared by the garments
        self.pose = BodyPose(body_mesh, any(m.settings.needs_face_tree for m in outfit.models),
                             any(m.settings.union_passes > 0 for m in outfit.models),
                             any(sf.model.settings.tip_share > 0 or sf.model.settings.cover_tips
                                 for sf in self.surfaces))
        self.profile = False
        self.stage_seconds = np.zeros((len(self.sims), 2))
        self.cloth_seconds = np.zeros(len(self.sims))

    def step_cloth(self, body_vertices: np.ndarray, dt: float, surface: bool = True,
                   surface_dt: float | None = None,
                   on_garment: Callable[[int, np.ndarray], None] | None = None,
                   coarse: bool = True) -> list[np.ndarray]:
        """One frame of every garment: S101, then (if `surface`) S102-S106 with time step
        `surface_dt` (default dt; longer when frames were skipped for the surface).

        The garments are independent given the body, and every kernel releases the GIL, so with
        `threads` > 1 they run on separate cores (the result is the same bit for bit). The body
        pose's grid and face tree (needed only by the contact passes at the end of S101) are
        updated on the calling thread while the helpers' garments start.
        on_garment(k, positions): called on the thread that stepped garment k, as soon as it is
        done (a service publishes it there while the other garments are still stepping); its
        detailed surface is `garment_surface(k)`. A garment worn over or under another
        (`self.layers`) is handed over on the calling thread once every garment is done and the
        pair's surfaces are layered.
        coarse False: S101 is not stepped; the detailed surfaces are built over the coarse cloth as
        it is (`services.warmup` compiles S102-S106 so, without S101's kernels)."""
        surface = surface and bool(self.surfaces)
        self.pose.update_surface(body_vertices, tips=surface)
        if coarse:  # before any garment steps: what an outer garment meets does not depend on the threads
            for m, s in self.over:
                carry_inner(m, s, self.sims[m.inner].state, self.pose.x, self.body_mesh.triangles, self.pose.face_n)
        self._frame = (body_vertices, dt, surface, surface_dt or dt, on_garment, coarse)
        helpers = self._pool.acquire() if self._pool is not None and self._threads > 1 else None
        order = sorted(range(len(self.sims)), key=self.garment_seconds.__getitem__)
        if order != self._order:
            self._order, self._shares = order, self._share_out(order)
        shares = self._shares[min(self._threads, 1 + len(helpers)) if helpers else 1]
        out: list = [None] * len(self.sims)
        submitted, failed = [], []
        # the helpers are kept for the layering only where a helper measures half of a garment (two tops)
        keep = helpers is not None and surface and self._split_layers
        try:
            try:
                for helper, share in zip(helpers or [], shares[1:]):
                    helper.submit(self._step_share, share)
                    submitted.append((helper, share))
                self.pose.update_queries()
                for k in shares[0]:
                    out[k] = self._step_garment(k)
            finally:
                # every call handed out is taken back, even after a failure, so the pool goes back idle
                for helper, share in submitted:
                    try:
                        for k, x in zip(share, helper.result()):
                            out[k] = x
                    except Exception as err:  # noqa: BLE001 - raised below, after the others are in
                        failed.append(err)
                if helpers is not None and not keep:
                    self._pool.release()
            if failed:
                raise failed[0]
            if surface:
                self._stack_layers(helpers[0] if keep and helpers else None)
        finally:
            if keep:
                self._pool.release()
        if surface:
            self.detailed = [self._detailed[k] for k in range(len(self.sims))]
            if on_garment is not None:
                for k in sorted(self.layered_garments):
                    on_garment(k, out[k])
        return out

    @property
    def level(self) -> int | None:
        """The detailed surfaces' tessellation level (None: coarse cloth only)."""
        return self.surfaces[0].model.tess.level if self.surfaces else None

    def models_at(self, level: int) -> tuple[list, list[LayerModel]] | None:
        """The surface models and layer pairs of a level this session used before (None: not used)."""
        if level == self.level:
            return [sf.model for sf in self.surfaces], [lm for lm, _ in self.layers]
        if level not in self._by_level:
            return None
        surfaces, pairs, _ = self._by_level[level]
        return [sf.model for sf in surfaces], [lm for lm, _ in pairs]

    def change_level(self, surface_models: list, layers: list[LayerModel]) -> None:
        """Go on with the detailed surfaces of another tessellation level (a live session holding
        its frame time, `services.frame_budget`): the coarse cloth steps on as it was, each
        garment's Δh is carried over onto the new particles (`DetailedSurface.carry_heights_from`)
        and the layering starts afresh. surface_models, layers: that level's, of the same outfit
        (`build_outfit`). A level used before takes up the surfaces it had, in place (a snapshot
        taken there restores onto them again)."""
        if not self.surfaces:
            raise ValueError("change_level: this session has no detailed surface")
        if len(surface_models) != len(self.surfaces):
            raise ValueError(f"change_level: {len(surface_models)} surface models for {len(self.surfaces)} garments")
        level = surface_models[0].tess.level
        if level == self.level:
            return
        self._by_level[self.level] = (self.surfaces, self.layers, self._split_layers)
        used = level in self._by_level
        if used:
            surfaces, pairs, split = self._by_level.pop(level)
            for lm, ls in pairs:  # (afresh, in place)
                StateSnapshot(LayerState(lm)).onto(ls).restore()
        else:
            surfaces = [DetailedSurface(sm) for sm in surface_models]
            pairs = [(lm, LayerState(lm)) for lm in layers]
            split = any(max(len(lm.over.candidates), len(lm.under.candidates)) >= SPLIT_CANDIDATES for lm in layers)
        for new, old in zip(surfaces, self.surfaces):
            new.carry_heights_from(old, afresh=used)
        self.surfaces, self.layers, self._split_layers = surfaces, pairs, split
        self._detailed = [None] * len(self.sims)
        self.detailed = []
        self.surface_seconds[:] = 0.0

    def _stack_layers(self, helper) -> None:
        """The layering of every pair (`cloth.layers.stack_layer`), after every garment has stepped;
        helper: an idle helper thread, which measures half of a garment with many candidates (two tops)."""
        t0 = time.perf_counter()
        body = None if self.pose.winding is None else (self.pose.x, self.body_mesh.winding_faces,
                                                       *self.pose.winding.arrays())
        for lm, ls in self.layers:
            (p_out, n_out), (p_in, n_in) = self._detailed[lm.outer], self._detailed[lm.inner]
            outer, inner = self.surfaces[lm.outer], self.surfaces[lm.inner]
            stack_layer(lm, ls, p_out, n_out, p_in, n_in, outer.state, inner.state, outer.model.settings.max_height,
                        body, helper)
        self.layer_seconds = time.perf_counter() - t0

    def garment_surface(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Garment k's detailed (positions, normals) of the frame last stepped."""
        return self._detailed[k]

    def _share_out(self, order: list[int]) -> dict[int, list[list[int]]]:
        """For n = 1 (helpers busy) .. threads: the garments of each thread, dealt out in `order`."""
        return {n: [order[r::n] for r in range(n)] for n in range(1, self._threads + 1)}

    def _step_share(self, share: list[int]) -> list[np.ndarray]:
        return [self._step_garment(k) for k in share]

    def _step_garment(self, k: int) -> np.ndarray:
        body_vertices, dt, surface, surface_dt, on_garment, coarse = self._frame
        sim = self.sims[k]
        t0 = time.perf_counter()
        if coarse:
            x = sim.step(body_vertices, dt, profile=self.profile, body_pose=self.pose)
        else:
            self.pose.wait_queries()  # (S101 waits for them in its step: the surface needs them too)
            x = sim.state.x
        self.cloth_seconds[k] = time.perf_counter() - t0
        self.stage_seconds[k] = sim.stage_seconds
        if surface:
            st, surf = sim.state, self.surfaces[k]
            self._detailed[k] = surf.step(x, st.nearest_any, self.pose.x, self.body_mesh, self.pose.face_n,
                                          surface_dt, self.pose.grid, self.pose.face_tips(),
                                          self.pose.winding.arrays() if self.pose.winding is not None else None,
                                          self.pose.faces.arrays() if self.pose.faces is not None else None,
                                          self.pose.vertex_tip)
            self.surface_seconds[k] = surf.stage_seconds
        spent = time.perf_counter() - t0
        avg = self.garment_seconds[k]
        self.garment_seconds[k] = spent if avg == 0.0 else avg + 0.1 * (spent - avg)
        if on_garment is not None and not (surface and k in self.layered_garments):
            on_garment(k, x)  # a layered garment's once it is layered (step_cloth)
        return x

    def close(self) -> None:
        if self._own_pool:
            self._pool.close()
        self._pool = None

    def snapshot(self) -> StateSnapshot:
        """Every garment's state as it is now (coarse, detailed, layering): `restore()` puts the
        session back to this moment, e.g. garments settled into a pose the motion comes back to.
        Stepping on from there gives what stepping on from here would, bit for bit."""
        return StateSnapshot(*self.states())

    def states(self) -> tuple:
        """The objects holding every garment's per-frame state (coarse, detailed, layering)."""
        return (*(s.state for s in self.sims), *(sf.state for sf in self.surfaces), *(ls for _, ls in self.layers),
                *(s for _, s in self.over))

    def preroll(self, q_first: np.ndarray, dt: float, blend_seconds: float = 1.0, settle_seconds: float = 0.5,
                contact: bool = True, stop: Callable[[], bool] | None = None) -> bool:
        """Blend the body from rest to the first frame's pose, then hold it while the cloth settles.
        contact: pose the blend with the animator's skin contact (as the session's frames are);
        the caller keeps the animator to itself meanwhile (its frame buffer is read through the hold);
        stop: asked before each step, True abandons the pre-roll (the session is not settled).
        Returns whether it ran to the end."""
        model = self.animator.character.model
        q_rest = self.animator.rest_configuration()
        n_blend = max(1, int(round(blend_seconds / dt)))
        n_settle = max(1, int(round(settle_seconds / dt)))
        n = n_blend + n_settle
        for k in range(1, n + 1):
            if stop is not None and stop():
                return False
            if k <= n_blend:  # held after the blend: the body posed last (the animator's own buffer)
                t = smoothstep(min(1.0, k / n_blend))
                q = pin.interpolate(model, q_rest, q_first, t)
                frame = self.animator.pose(q, contact=contact)
            # the detailed surface only needs the last few steps to settle onto the coarse cloth
            self.step_cloth(frame.vertices, dt, surface=k > n - self.PREROLL_SURFACE_STEPS)
        return True


def run_cloth_clip(body: Body, outfit_dir: Path, clip: Path, every: int = 2, max_frames: int | None = None,
                   snapshot_frames: list[int] | None = None, settings: SimSettings | None = None,
                   fabrics=None, profile: bool = False, on_frame=None,
                   surface: SurfaceSettings | None = None, ik: IKSettings | None = None,
                   contact: ContactSettings | None = ContactSettings()) -> ClothReport:
    """Run an outfit through a clip. on_frame(index, session, body_frame, positions) sees every frame."""
    wanted = set(snapshot_frames or [])
    with BVHSource(clip, every=every, max_frames=max_frames) as source:
        animator = BodyAnimator(body, source.skeleton, ik=ik, contact=contact)
        body_mesh = collision_body(body)
        outfit, surface_models, layers = build_outfit(body, animator, body_mesh, Path(outfit_dir), fabrics, settings,
                                                      surface, ModelCache.from_env())
        # garments one after the other: the per-garment stage timings stay those of one core
        session = OutfitSession(body, animator, body_mesh, outfit, surface_models=surface_models, threads=1,
                                layers=layers)
        session.profile = profile
        report = ClothReport(Path(clip).stem, outfit.name, [m.name for m in outfit.models], models=outfit.models)
        report.surface_triangles = [sf.model.tess.triangles for sf in session.surfaces]
        stage = {f"{g}": [] for g in report.garments}
        dt = source.frame_time
        started = False
        for frame in source:
            if frame.index < START_FRAME:
                continue
            body_frame = animator(frame.local_rot, frame.root_position)
            if not started:
                session.preroll(body_frame.retarget.q.copy(), dt)
                body_frame = animator.pose(body_frame.retarget.q)
                started = True
            positions = session.step_cloth(body_frame.vertices, dt)
            for k, (name, sec) in enumerate(zip(report.garments, session.cloth_seconds)):
                stage[name].append(sec * 1000)
                if profile:
                    report.split_ms.setdefault(name, []).append(tuple(session.stage_seconds[k] * 1000))
                if surface is not None:
                    report.surface_ms.setdefault(name, []).append(tuple(session.surface_seconds[k] * 1000))
            if session.layers:
                report.layer_ms.append(session.layer_seconds * 1000)
            if not all(np.isfinite(p).all() for p in positions):
                report.nan_frames += 1
            if on_frame is not None:
                on_frame(frame.index, session, body_frame, positions)
            if frame.index in wanted:
                report.snapshots.append((frame.index, body_frame.vertices[: body.n_visible].copy(),
                                         [p.copy() for p in positions]))
                report.detailed_snapshots.append([(p.copy(), n.copy()) for p, n in session.detailed])
            report.frames += 1
        report.stage_ms = {k: np.array(v) for k, v in stage.items()}
        report.substeps = [s.stats.last_substeps for s in session.sims]
        report.resets = [s.stats.reset_particles for s in session.sims]
    return report


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals for drawing (cloth.geometry's kernel)."""
    out = np.empty((len(vertices), 3))
    geometry_vertex_normals(np.ascontiguousarray(vertices, dtype=np.float64), triangles, out)
    return out


def render_cloth_snapshots(body: Body, report: ClothReport, models: list[ClothModel], out_dir: Path,
                           renderer=None, azimuths=(0.0, 150.0), close_up: bool = False) -> Path:
    """One contact sheet per clip × outfit: each snapshot frame from two sides (close_up: the
    middle of the body from 1.6 m instead of all of it from 3.6 m, at 600 × 800 pixels)."""
    from .body_job import SKIN
    from .render import MeshDraw, Renderer, contact_sheet, orbit_camera, save_png

    own = renderer is None or close_up
    renderer = Renderer(600, 800) if close_up else renderer or Renderer(360, 480)
    distance, height, middle = (1.6, 0.1, 0.45) if close_up else (3.6, 0.2, 0.5)
    images = []
    for s, (_, verts, garments) in enumerate(report.snapshots):
        meshes = [MeshDraw(verts, body.triangles, vertex_normals(verts, body.triangles), SKIN)]
        detailed = report.detailed_snapshots[s] if s < len(report.detailed_snapshots) else []
        for k, (m, x) in enumerate(zip(models, garments)):
            if detailed and report.surface_triangles:
                p, n = detailed[k]  # the detailed surface with its S106 shading normals
                meshes.append(MeshDraw(p, report.surface_triangles[k], n, GARMENT_COLORS[k % 4]))
            else:
                meshes.append(MeshDraw(x, m.triangles, vertex_normals(x, m.triangles), GARMENT_COLORS[k % 4]))
        centre = np.array([verts[:, 0].mean(), verts[:, 1].min() + middle * np.ptp(verts[:, 1]), verts[:, 2].mean()])
        for az in azimuths:
            images.append(renderer.render(meshes, orbit_camera(centre, az, distance=distance, height=height)))
    if own:
        renderer.release()
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"cloth_{report.clip}_{report.outfit}{'_close' if close_up else ''}.png"
    save_png(path, contact_sheet(images, columns=4))
    return path
