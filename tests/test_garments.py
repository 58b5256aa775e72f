"""Garment loading (mhclo fit, split), coarse models, and outfits on a real clip."""

import numpy as np
import pytest

from cloth.coarsen import _cross, coarsen, spatial_order
from cloth.geometry import morton_order
from cloth.garment import GarmentError, fit_mhclo, load_garment_file, load_outfit, read_mhclo
from cloth.topology import boundary_loops, orient_faces, polygon_edges, triangulate

OUTFITS = ["female_casualsuit01", "female_elegantsuit01", "female_sportsuit01"]
SIZES = {  # authored vertices per component (data README)
    "female_elegantsuit01": (1810, 395),
    "female_casualsuit01": (1311, 886),
    "female_sportsuit01": (911, 886),
}


@pytest.fixture(scope="module")
def outfits(body, data):
    return {o: load_outfit(data / "garments" / o, body.vertices) for o in OUTFITS}


def test_mhclo_fit_formula_on_a_hand_made_base(tmp_path):
    clo = tmp_path / "t.mhclo"
    clo.write_text("name t\nobj_file t.obj\nx_scale 0 1 2.0\ny_scale 0 2 4.0\nz_scale 1 2 1.0\nverts 0\n"
                   "0 1 2 0.5 0.25 0.25 1.0 1.0 1.0\n2\n")
    base = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 1.0], [0.0, 4.0, 3.0]])
    fitted = fit_mhclo(read_mhclo(clo), base)
    # scales: x |0-2|/2 = 1, y |0-4|/4 = 1, z |1-3|/1 = 2
    np.testing.assert_allclose(fitted[0], 0.5 * base[0] + 0.25 * base[1] + 0.25 * base[2] + [1.0, 1.0, 2.0])
    np.testing.assert_allclose(fitted[1], base[2])


@pytest.mark.parametrize("text, problem", [
    ("obj_file t.obj\nx_scale 0 1 2\ny_scale 0 1 2\nverts 0\n0 1 2 1 0 0 0 0 0\n", "z_scale"),
    ("obj_file t.obj\nx_scale 0 1 2\ny_scale 0 1 2\nz_scale 0 1 2\nverts 0\n0 1 2 1 0\n", ":6: vertex row needs"),
    ("obj_file t.obj\nx_scale 0 1 2\ny_scale 0 1 2\nz_scale 0 1 2\nverts 0\n0 1 2 0.2 0.2 0.2 0 0 0\n", "sum to 1"),
    ("x_scale 0 1 2\ny_scale 0 1 2\nz_scale 0 1 2\nverts 0\n0 1 2 1 0 0 0 0 0\n", "no obj_file"),
])
def test_malformed_mhclo_is_rejected_with_file_and_problem(tmp_path, text, problem):
    path = tmp_path / "bad.mhclo"
    path.write_text(text)
    with pytest.raises(GarmentError, match="bad.mhclo") as err:
        read_mhclo(path)
    assert problem in str(err.value)


def test_an_obj_polygon_of_more_than_four_corners_is_read_as_a_fan_of_triangles(tmp_path):
    """A modelling tool's OBJ may hold n-gons: a regular hexagon beside a quad and a triangle comes back
    as four triangles fanned from its first corner (covering its area, 3 sqrt(3) / 2 r^2), the quad and
    the triangle as they are; a face of two corners is refused naming the file."""
    from cloth.garment import read_obj_polygons

    hexagon = [(np.cos(a), np.sin(a), 0.0) for a in np.arange(6) * np.pi / 3]
    extra = [(3.0, 0.0, 0.0), (4.0, 0.0, 0.0), (4.0, 1.0, 0.0), (3.0, 1.0, 0.0), (5.0, 0.0, 0.0)]
    path = tmp_path / "ngon.obj"
    path.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in hexagon + extra)
                    + "f 1 2 3 4 5 6\nf 7 8 9 10\nf 8 11 9\n")
    vertices, faces = read_obj_polygons(path)
    np.testing.assert_array_equal(faces, [[0, 1, 2, -1], [0, 2, 3, -1], [0, 3, 4, -1], [0, 4, 5, -1],
                                          [6, 7, 8, 9], [7, 10, 8, -1]])
    tri = vertices[faces[:4, :3]]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    assert area == pytest.approx(3 * np.sqrt(3) / 2)
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2\n")
    with pytest.raises(GarmentError, match=r"ngon\.obj: face 1 has 2 vertices; a face needs three or more"):
        read_obj_polygons(path)


def test_outfits_split_into_top_and_bottom_with_consistent_winding(outfits):
    for name, garments in outfits.items():
        assert [g.name for g in garments] == [f"{name}.top", f"{name}.bottom"]
        assert tuple(len(g.vertices) for g in garments) == SIZES[name]
        top, bottom = garments
        assert top.vertices[:, 1].mean() > bottom.vertices[:, 1].mean()
        for g in garments:
            directed = polygon_edges(g.faces)
            assert len(np.unique(directed, axis=0)) == len(directed)  # no edge used twice in one direction


def test_orient_faces_repairs_a_flipped_face():
    faces = np.array([[0, 1, 2, 3], [1, 4, 5, 2], [4, 6, 7, 5]])
    faces[1] = faces[1][::-1]
    fixed = orient_faces(faces)
    np.testing.assert_array_equal(fixed[1], [1, 4, 5, 2])
    np.testing.assert_array_equal(fixed[0], faces[0])


def test_coarse_models_are_quad_dominant_and_keep_every_boundary(outfits):
    for garments in outfits.values():
        for g in garments:
            c = coarsen(g.vertices, g.faces, 360)
            assert 300 <= len(c.vertices) <= 400
            assert c.n_quads > c.n_triangles
            assert len(boundary_loops(c.faces)) == len(g.boundary_loops)
            edges = np.sort(polygon_edges(c.faces), axis=1)
            _, counts = np.unique(edges, axis=0, return_counts=True)
            assert counts.max() <= 2  # manifold
            # every authored vertex maps onto the coarse surface close by
            tris, _ = triangulate(c.faces, c.vertices)
            mapped = np.einsum("nk,nkd->nd", c.fine_bary, c.vertices[tris[c.fine_triangle]])
            # 4 cm coarse edges on curved cloth: chord deviation of a centimetre or two
            assert np.percentile(np.linalg.norm(mapped - g.vertices, axis=1), 95) < 0.02


def test_the_coarsening_cross_product_is_numpys_bit_for_bit():
    """The coarsening's collapse tests take u x v thousands of times on 3-vectors; written out, it
    must give np.cross's bits, or the coarse meshes (and every result after them) would move."""
    rng = np.random.default_rng(7)
    u, v = rng.normal(size=(2000, 3)) * rng.uniform(1e-4, 10, (2000, 1)), rng.normal(size=(2000, 3))
    for a, b in zip(u, v):
        assert np.array_equal(_cross(a, b), np.cross(a, b))
    np.testing.assert_array_equal(_cross(np.array([1.0, 0, 0]), np.array([0, 1.0, 0])), [0, 0, 1.0])


def test_morton_order_follows_the_z_curve_and_spatial_order_keeps_the_mesh():
    """A 2 x 2 block of cells, x bit first: (0,0), (1,0), (0,1), (1,1); then the next block
    along x. spatial_order renumbers a shuffled 4 x 4 sheet: the same faces as corner positions
    (same winding), vertices and faces in Z order, consecutive vertices neighbours."""
    c = 0.02
    pts = np.array([[1, 1, 0], [2, 0, 0], [0, 1, 0], [1, 0, 0], [0, 0, 0]], float) * c + 0.005
    np.testing.assert_array_equal(morton_order(pts, c), [4, 3, 2, 0, 1])
    rng = np.random.default_rng(3)
    grid = np.array([[i, j, 0.0] for j in range(4) for i in range(4)]) * c
    quads = np.array([[j * 4 + i, j * 4 + i + 1, j * 4 + i + 5, j * 4 + i + 4] for j in range(3) for i in range(3)])
    perm = rng.permutation(16)  # shuffled numbering: vertex perm[k] is grid point k
    verts = np.empty_like(grid)
    verts[perm] = grid
    faces = perm[quads]
    faces[4, 3] = -1  # one triangle
    v2, f2 = spatial_order(verts, faces)
    as_points = lambda v, f: sorted(tuple(map(tuple, np.round(v[row[row >= 0]] / c).astype(int))) for row in f)
    assert as_points(v2, f2) == as_points(verts, faces)
    np.testing.assert_array_equal(morton_order(v2, c), np.arange(16))
    assert np.all(np.linalg.norm(np.diff(v2[:4], axis=0), axis=1) <= c * np.sqrt(2) + 1e-12)
    centres = np.array([v2[row[row >= 0]].mean(axis=0) for row in f2])
    np.testing.assert_array_equal(morton_order(centres, c), np.arange(9))


def test_any_trimesh_mesh_is_accepted(tmp_path):
    import trimesh

    a = trimesh.creation.icosphere(subdivisions=1, radius=0.2)
    b = trimesh.creation.icosphere(subdivisions=1, radius=0.2)
    b.apply_translation([0, -0.5, 0])
    path = tmp_path / "two.ply"
    trimesh.util.concatenate([a, b]).export(path)
    garments = load_garment_file(path)
    assert [g.name for g in garments] == ["two.top", "two.bottom"]
    assert len(garments[0].vertices) == 42
    with pytest.raises(GarmentError, match="no such file"):
        load_garment_file(tmp_path / "missing.glb")


def test_a_garment_wound_inwards_is_turned_to_face_away_from_the_body(outfits, body):
    """A sleeve (an open cylinder of quads, r = 6 cm) around a body cylinder (r = 5 cm): wound so
    its normals point in, face_outward reverses every face (padding kept), after which every
    normal points away from the axis; wound outwards, it is returned as it is. The shipped
    garments all face out already."""
    from cloth.garment import Garment, face_outward

    def cylinder(r, n=24, rows=6):
        t = np.linspace(0, 2 * np.pi, n, endpoint=False)
        v = np.array([[r * np.cos(a), 0.05 * k, r * np.sin(a)] for k in range(rows) for a in t])
        f = [[k * n + i, k * n + (i + 1) % n, (k + 1) * n + (i + 1) % n, (k + 1) * n + i]
             for k in range(rows - 1) for i in range(n)]
        return v, np.array(f, dtype=np.int32)

    skin, _ = cylinder(0.05, n=48, rows=11)
    v, f = cylinder(0.06)

    def outward_share(g):
        a, b, c = (g.vertices[g.faces[:, k]] for k in range(3))
        n = np.cross(b - a, c - a)
        radial = (a + b + c) / 3 * [1.0, 0.0, 1.0]
        return np.mean(np.einsum("ij,ij->i", n, radial) > 0)

    f_out = f if outward_share(Garment("s", v, f, np.arange(len(v)))) > 0.5 else f[:, ::-1].copy()
    f_in = f_out[:, ::-1].copy()
    f_in_tri = np.concatenate([f_in, np.c_[f_in[:3, :3], np.full(3, -1)]]).astype(np.int32)  # some triangles too
    sleeve_out, sleeve_in = Garment("s", v, f_out, np.arange(len(v))), Garment("s", v, f_in_tri, np.arange(len(v)))
    assert outward_share(sleeve_out) == 1.0 and outward_share(sleeve_in) == 0.0
    assert face_outward(sleeve_out, skin) is sleeve_out
    turned = face_outward(sleeve_in, skin)
    assert outward_share(turned) == 1.0
    np.testing.assert_array_equal(turned.faces[-3:, 3], -1)
    np.testing.assert_array_equal(np.sort(turned.faces, axis=1), np.sort(sleeve_in.faces, axis=1))  # same faces
    for outfit in OUTFITS:
        for g in outfits[outfit]:
            assert face_outward(g, body.vertices[: body.n_visible]) is g, g.name


def _write_obj(path, vertices, faces):
    """An OBJ of quads and triangles (faces padded with -1), coordinates as Python writes floats."""
    with open(path, "w") as f:
        f.writelines(f"v {x!r} {y!r} {z!r}\n" for x, y, z in vertices.tolist())
        f.writelines("f " + " ".join(str(i + 1) for i in row if i >= 0) + "\n" for row in faces.tolist())


@pytest.fixture(scope="module")
def rest_world(body):
    """The body at rest in the world frame (feet on y = 0) as the garments are fitted: all of
    base.obj's vertices, and the visible skin's."""
    from skinning.animate import BodyAnimator

    base = body.vertices + BodyAnimator(body, contact=None).world_offset
    return base, base[: body.n_visible]


def test_an_outfit_is_a_makehuman_folder_a_garment_mesh_or_a_folder_of_them(data, rest_world, tmp_path):
    """A user's garments, already on the rest body: one mesh file (one garment, named after the
    file, or a garment per connected piece), or a folder of them, load where they are; the casual
    outfit's T-shirt written as an OBJ of quads and its jeans as a PLY of triangles come back as
    the .mhclo fitting gives them. A garment that reaches no higher than the waist hangs from it
    (its waistband grips): the jeans, every shipped bottom, and no shipped top."""
    import trimesh

    from cloth.garment import load_garments, worn_from_waist

    base, skin = rest_world
    tee, jeans = load_outfit(data / "garments" / "female_casualsuit01", base)
    _write_obj(tmp_path / "tee.obj", tee.vertices, tee.faces)
    tris, _ = triangulate(jeans.faces, jeans.vertices)
    trimesh.Trimesh(jeans.vertices, tris, process=False).export(tmp_path / "jeans.ply")

    (one,) = load_garments(tmp_path / "tee.obj", base, skin)
    assert one.name == "tee"
    np.testing.assert_array_equal(one.vertices, tee.vertices)
    np.testing.assert_array_equal(one.faces, tee.faces)  # quads kept
    both = load_garments(tmp_path, base, skin)
    assert [g.name for g in both] == ["jeans", "tee"]  # the files in name order
    np.testing.assert_allclose(both[0].vertices[np.argsort(both[0].source_ids)], jeans.vertices, atol=1e-6)
    assert [worn_from_waist(g, skin) for g in both] == [True, False]
    fitted = load_garments(data / "garments" / "female_casualsuit01", base, skin)  # the .mhclo: fitted as before
    np.testing.assert_array_equal(fitted[1].vertices, jeans.vertices)
    for outfit in OUTFITS:
        for g in load_outfit(data / "garments" / outfit, base):
            assert worn_from_waist(g, skin) == g.name.endswith(".bottom"), g.name


def test_a_garment_mesh_off_the_rest_body_or_no_outfit_at_all_is_refused_naming_it(data, rest_world, tmp_path):
    """A garment mesh in other units or another frame is refused, naming the file and the frame
    expected, rather than simulated from where it floats; so is a path that holds no outfit. A
    file's name becomes the garment's (a bus key: letters, digits, '_', '.' and '-'), and two
    files giving one name are refused; so is a mesh with a coordinate that is not a number."""
    import trimesh

    from cloth.garment import load_garments

    base, skin = rest_world
    tee = load_outfit(data / "garments" / "female_casualsuit01", base)[0]
    for name, vertices in (("decimetres", tee.vertices * 10.0), ("beside", tee.vertices + [0.5, 0.0, 0.0])):
        _write_obj(tmp_path / f"{name}.obj", vertices, tee.faces)
        with pytest.raises(GarmentError, match=rf"{name}\.obj: garment '{name}' does not lie on the rest body"
                                               r".* in metres, in the rest body's frame"):
            load_garments(tmp_path / f"{name}.obj", base, skin)
    (tmp_path / "empty").mkdir()
    with pytest.raises(GarmentError, match="empty: no .mhclo file and no garment mesh"):
        load_garments(tmp_path / "empty", base, skin)
    (tmp_path / "notes.txt").write_text("a shirt")
    with pytest.raises(GarmentError, match=r"notes\.txt: not a garment mesh"):
        load_garments(tmp_path / "notes.txt", base, skin)
    with pytest.raises(GarmentError, match="missing: no such file or folder"):
        load_garments(tmp_path / "missing", base, skin)
    _write_obj(tmp_path / "button.obj", tee.vertices[:3], np.array([[0, 1, 2, -1]]))
    with pytest.raises(GarmentError, match=r"button\.obj: no piece of cloth in it"):
        load_garments(tmp_path / "button.obj", base, skin)
    # a coordinate that is not a number: named, in an OBJ as in any other format (the placement
    # check read "more than nan cm from the skin", after trimesh warned while merging it)
    holed = tee.vertices.copy()
    holed[10, 1], holed[11, 2] = np.nan, np.inf
    _write_obj(tmp_path / "holed.obj", holed, tee.faces)
    tris, _ = triangulate(tee.faces, tee.vertices)
    trimesh.Trimesh(holed, tris, process=False).export(tmp_path / "holed.ply")
    for f in ("holed.obj", "holed.ply"):
        with pytest.raises(GarmentError, match=rf"{f.replace('.', '[.]')}: vertex 10 has a coordinate that is not a "
                                               r"finite number \(.*nan.*\), and 1 more vertices"):
            load_garments(tmp_path / f, base, skin)
    mine = tmp_path / "mine"
    mine.mkdir()
    _write_obj(mine / "my shirt.obj", tee.vertices, tee.faces)
    assert [g.name for g in load_garments(mine, base, skin)] == ["my_shirt"]
    _write_obj(mine / "my_shirt.obj", tee.vertices, tee.faces)
    with pytest.raises(GarmentError, match="a garment named 'my_shirt' came from another file"):
        load_garments(mine, base, skin)


def test_an_outfit_folder_names_its_garments_fabrics(body, data, rest_world, tmp_path):
    """fabrics.toml in an outfit's folder: each garment named under [garments] is made of that
    fabric (a preset, or one the file defines); one not named keeps the default; a name the outfit
    lacks, a fabric nobody defines, or no [garments] table is refused naming the file and key."""
    from cloth.fabric import FabricError, fabric, outfit_fabrics
    from services.cloth_job import collision_body, load_outfit_models
    from skinning.animate import BodyAnimator

    base, _ = rest_world
    tee, jeans = load_outfit(data / "garments" / "female_casualsuit01", base)
    _write_obj(tmp_path / "tee.obj", tee.vertices, tee.faces)
    _write_obj(tmp_path / "jeans.obj", jeans.vertices, jeans.faces)
    stiff = "\n".join(f"{k} = {v!r}" for k, v in vars(fabric("denim")).items() if k != "name")
    (tmp_path / "fabrics.toml").write_text(f'[garments]\njeans = "raw_denim"\n\n[raw_denim]\n{stiff}\n')
    outfit = load_outfit_models(body, BodyAnimator(body, contact=None), collision_body(body), tmp_path)
    made = {m.name: m.fabric for m in outfit.models}
    assert made["jeans"].name == "raw_denim" and made["jeans"].stretch_stiffness == fabric("denim").stretch_stiffness
    assert made["tee"] == fabric("cotton")
    assert {m.name: bool(m.grip.any()) for m in outfit.models} == {"jeans": True, "tee": False}  # the waistband

    (tmp_path / "fabrics.toml").write_text('[garments]\nskirt = "silk"\n')
    with pytest.raises(FabricError, match=r"fabrics\.toml: \[garments\] names \['skirt'\], which the outfit does not"):
        load_outfit_models(body, BodyAnimator(body, contact=None), collision_body(body), tmp_path)
    for text, says in (('[garments]\njeans = "tweed"\n', r"\[garments\]\.jeans: no fabric 'tweed'; available: \["),
                       ('jeans = "denim"\n', r"needs a table \[garments\]"),
                       ('[garments\n', "not valid TOML")):
        (tmp_path / "fabrics.toml").write_text(text)
        with pytest.raises(FabricError, match=says):
            outfit_fabrics(tmp_path / "fabrics.toml")


def test_a_fabric_per_garment_from_the_command_line(body, data, rest_world, tmp_path):
    """`--fabric top=silk,bottom=denim` (`fabric_choice`): one fabric per garment, a garment by its
    whole name or by what follows its outfit's name; the garments it does not name keep theirs
    (the outfit folder's fabrics.toml, else the default); one name alone is a fabric for every
    garment. A malformed pair, an unknown fabric, a garment named twice or one the outfit lacks is
    refused, naming it."""
    from cloth.fabric import Fabric, FabricError, fabric, fabric_choice, garment_fabrics
    from services.cloth_job import collision_body, load_outfit_models
    from skinning.animate import BodyAnimator

    assert fabric_choice("denim") == fabric("denim")
    choice = fabric_choice(" top = silk ,female_casualsuit01.bottom=jersey")
    assert choice == {"top": fabric("silk"), "female_casualsuit01.bottom": fabric("jersey")}
    for text, says in (("top=silk,bottom", r"'bottom' is not garment=fabric"), ("top=", "is not garment=fabric"),
                       ("top=velvet", r"top=velvet: .*no fabric 'velvet'; available: \["),
                       ("top=silk,top=denim", "garment 'top' is named twice"), ("velvet", "no fabric 'velvet'")):
        with pytest.raises(FabricError, match=says):
            fabric_choice(text)
    names = ["female_casualsuit01.top", "female_casualsuit01.bottom"]
    assert garment_fabrics(choice, names) == {"female_casualsuit01.top": fabric("silk"),
                                              "female_casualsuit01.bottom": fabric("jersey")}
    with pytest.raises(FabricError, match=r"no garment 'legs' in the outfit; it has \['female_casualsuit01.top'"):
        garment_fabrics({"legs": fabric("silk")}, names)
    with pytest.raises(FabricError, match=r"'top' names several garments"):
        garment_fabrics({"top": fabric("silk")}, ["a.top", "b.top"])

    animator, mesh = BodyAnimator(body, contact=None), collision_body(body)
    shipped = load_outfit_models(body, animator, mesh, data / "garments" / "female_casualsuit01",
                                 fabric_choice("top=silk"))
    assert {m.name: m.fabric.name for m in shipped.models} == {"female_casualsuit01.top": "silk",
                                                               "female_casualsuit01.bottom": "denim"}
    assert isinstance(shipped.models[0].fabric, Fabric)
    base, _ = rest_world
    tee, jeans = load_outfit(data / "garments" / "female_casualsuit01", base)
    _write_obj(tmp_path / "tee.obj", tee.vertices, tee.faces)
    _write_obj(tmp_path / "jeans.obj", jeans.vertices, jeans.faces)
    (tmp_path / "fabrics.toml").write_text('[garments]\njeans = "jersey"\ntee = "silk"\n')
    mine = load_outfit_models(body, animator, mesh, tmp_path, fabric_choice("tee=denim"))
    assert {m.name: m.fabric.name for m in mine.models} == {"tee": "denim", "jeans": "jersey"}
    with pytest.raises(FabricError, match=r"no garment 'top' in the outfit; it has \['"):
        load_outfit_models(body, animator, mesh, tmp_path, fabric_choice("top=denim"))


def test_an_outfit_mixed_from_others_garments(body, data, rest_world, tmp_path):
    """`female_casualsuit01.top+female_elegantsuit01.bottom`: the T-shirt of one outfit with the
    skirt of another, each as its own outfit fits it, with its default fabric and its waistband;
    a term may be a whole outfit, or a garment mesh file beside them. Each outfit's fabrics.toml
    gives the fabric of its garments taken (naming one not taken is no error). A term that is
    neither an outfit there nor a garment of one, a part an outfit lacks, or a garment taken
    twice is refused naming it."""
    import os

    from cloth.fabric import fabric
    from cloth.garment import load_garments, mix_terms
    from services.cloth_job import collision_body, find_outfit, load_outfit_models, outfit_digest
    from skinning.animate import BodyAnimator

    base, skin = rest_world
    garments = tmp_path / "garments"
    garments.mkdir()
    for outfit in OUTFITS:
        os.symlink(data / "garments" / outfit, garments / outfit)
    casual = load_outfit(garments / "female_casualsuit01", base)
    elegant = load_outfit(garments / "female_elegantsuit01", base)
    _write_obj(garments / "tee.obj", casual[0].vertices, casual[0].faces)

    mix = find_outfit(tmp_path, "female_casualsuit01.top+female_elegantsuit01.bottom")
    assert mix_terms(mix) == [(garments / "female_casualsuit01", "female_casualsuit01.top"),
                              (garments / "female_elegantsuit01", "female_elegantsuit01.bottom")]
    got = load_garments(mix, base, skin)
    assert [g.name for g in got] == ["female_casualsuit01.top", "female_elegantsuit01.bottom"]
    np.testing.assert_array_equal(got[0].vertices, casual[0].vertices)
    np.testing.assert_array_equal(got[1].faces, elegant[1].faces)
    models = load_outfit_models(body, BodyAnimator(body, contact=None), collision_body(body), mix).models
    assert [(m.fabric.name, bool(m.grip.any())) for m in models] == [("cotton", False), ("cotton", True)]
    whole = load_garments(find_outfit(tmp_path, "tee.obj+female_elegantsuit01"), base, skin)
    assert [g.name for g in whole] == ["tee", "female_elegantsuit01.top", "female_elegantsuit01.bottom"]
    assert outfit_digest(mix) != outfit_digest(find_outfit(tmp_path, "female_casualsuit01.top+female_sportsuit01"))

    # the skirt's outfit's own fabrics.toml names its blouse too, which the mix does not take
    own = tmp_path / "elegant"
    own.mkdir()
    for f in (data / "garments" / "female_elegantsuit01").iterdir():
        os.symlink(f, own / f.name)
    (own / "fabrics.toml").write_text('[garments]\n"elegant.bottom" = "denim"\n"elegant.top" = "silk"\n')
    os.symlink(own, garments / "elegant")
    models = load_outfit_models(body, BodyAnimator(body, contact=None), collision_body(body),
                                find_outfit(tmp_path, "female_casualsuit01.top+elegant.bottom")).models
    assert [m.fabric for m in models] == [fabric("cotton"), fabric("denim")]

    for name, says in (("female_casualsuit02.top+female_elegantsuit01", r"'female_casualsuit02.top' is neither an "
                        r"outfit in .*garments nor a garment of one .*; there are \['elegant', 'female_casualsuit01'"),
                       ("female_casualsuit01.top+", r"'' is neither an outfit")):
        with pytest.raises(GarmentError, match=says):
            find_outfit(tmp_path, name)
    for name, says in (("female_casualsuit01.shoes+female_elegantsuit01",
                        r"female_casualsuit01 has no garment 'female_casualsuit01.shoes'; it has "
                        r"\['female_casualsuit01.top', 'female_casualsuit01.bottom'\]"),
                       ("female_casualsuit01+female_casualsuit01.top",
                        "garment 'female_casualsuit01.top' comes twice")):
        with pytest.raises(GarmentError, match=says):
            load_garments(find_outfit(tmp_path, name), base, skin)


def test_of_two_garments_made_for_the_same_depth_the_later_is_worn_over_the_earlier(body, data, caplog):
    """The T-shirt and the silk blouse (`female_casualsuit01+female_elegantsuit01.top`): the two
    tops' coarse cloths lie within a centimetre of each other over most of both at rest: the
    blouse, named later, is worn over the T-shirt (its coarse cloth kept over the T-shirt's, and
    the detailed layering's pair the same way round), and the build says so. Named the other way
    round, the T-shirt is worn over the blouse. No shipped outfit's top and bottom are such a pair."""
    import logging

    from cloth.surface import SurfaceSettings
    from services.cloth_job import OUTFITS, build_outfit, collision_body, find_outfit
    from skinning.animate import BodyAnimator

    animator, body_mesh = BodyAnimator(body, contact=None), collision_body(body)
    for name in OUTFITS:
        outfit, _, _ = build_outfit(body, animator, body_mesh, find_outfit(data, name))
        assert outfit.over == [], name
    with caplog.at_level(logging.INFO, logger="tryon.cloth"):
        outfit, _, layers = build_outfit(body, animator, body_mesh,
                                         find_outfit(data, "female_casualsuit01+female_elegantsuit01.top"),
                                         surface=SurfaceSettings(level=3))
    names = [m.name for m in outfit.models]
    assert names == ["female_casualsuit01.top", "female_casualsuit01.bottom", "female_elegantsuit01.top"]
    assert [(m.outer, m.inner) for m in outfit.over] == [(2, 0)]
    assert min(outfit.over[0].overlap) > 0.5 and outfit.over[0].gap == outfit.models[2].fabric.thickness
    assert (2, 0) in {(m.outer, m.inner) for m in layers}
    said = [r.getMessage() for r in caplog.records if "is worn over" in r.getMessage()]
    assert said == [said[0]] and said[0].startswith("outfit female_casualsuit01+female_elegantsuit01.top: "
                                                    "female_elegantsuit01.top is worn over female_casualsuit01.top")
    outfit, _, _ = build_outfit(body, animator, body_mesh,
                                find_outfit(data, "female_elegantsuit01.top+female_casualsuit01.top"))
    assert [(m.outer, m.inner) for m in outfit.over] == [(1, 0)]
    assert outfit.models[1].name == "female_casualsuit01.top"
    # three tops: the T-shirt over the sports top (which lies within a centimetre of it, not it of the
    # sports top over most of it), the blouse over both
    outfit, _, _ = build_outfit(body, animator, body_mesh, find_outfit(
        data, "female_sportsuit01.top+female_casualsuit01.top+female_elegantsuit01.top"))
    assert [(m.outer, m.inner) for m in outfit.over] == [(1, 0), (2, 0), (2, 1)]


def test_in_a_folder_of_garment_meshes_the_later_file_name_is_worn_over(body, data, rest_world, tmp_path):
    """A user's folder with the T-shirt as 2_tee.obj and the blouse as 1_blouse.obj, both on the
    rest body: the tee, later by name, is worn over the blouse."""
    from services.cloth_job import collision_body, load_outfit_models
    from skinning.animate import BodyAnimator

    base, _ = rest_world
    tee = load_outfit(data / "garments" / "female_casualsuit01", base)[0]
    blouse = load_outfit(data / "garments" / "female_elegantsuit01", base)[0]
    _write_obj(tmp_path / "2_tee.obj", tee.vertices, tee.faces)
    _write_obj(tmp_path / "1_blouse.obj", blouse.vertices, blouse.faces)
    outfit = load_outfit_models(body, BodyAnimator(body, contact=None), collision_body(body), tmp_path)
    assert [m.name for m in outfit.models] == ["1_blouse", "2_tee"]
    assert [(m.outer, m.inner) for m in outfit.over] == [(1, 0)]
