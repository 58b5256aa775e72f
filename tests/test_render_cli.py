import numpy as np
import pytest
from PIL import Image

from services.cli import main
from services.render import MeshDraw, Renderer, contact_sheet, orbit_camera
from skinning.animate import BodyAnimator


def test_render_shows_the_body(body):
    animator = BodyAnimator(body)
    frame = animator.pose(animator.rest_configuration())
    r = Renderer(120, 160)
    vis = frame.vertices[: body.n_visible]
    cam = orbit_camera(np.array([0, 0.85, 0]), 0.0)
    with_body = r.render([MeshDraw(vis, body.triangles, frame.normals)], cam)
    empty = r.render([], cam)
    r.release()
    assert with_body.shape == (160, 120, 3)
    changed = np.abs(with_body.astype(int) - empty.astype(int)).sum(axis=2) > 30
    # the body covers a tall, centred, symmetric region of the picture
    rows, cols = np.nonzero(changed)
    assert changed.mean() > 0.05
    assert np.ptp(rows) > 0.6 * 160
    assert abs(cols.mean() - 60) < 6


def test_contact_sheet_tiles_without_empty_columns():
    images = [np.full((4, 3, 3), k, dtype=np.uint8) for k in range(5)]
    two = contact_sheet(images[:2], columns=4)  # fewer images than columns: one row of them
    assert two.shape == (4, 6, 3)
    np.testing.assert_array_equal(two[:, 3:], 1)
    five = contact_sheet(images, columns=4)
    assert five.shape == (8, 12, 3)
    np.testing.assert_array_equal(five[4:, :3], 4)
    np.testing.assert_array_equal(five[4:, 3:], 255)  # the rest of the last row is blank


def test_cli_body_writes_snapshots(tmp_path, capsys):
    rc = main(["body", "--clip", "cmu_npybvh_example_75f", "--out", str(tmp_path)])
    assert rc == 0
    out = capsys.readouterr().out
    assert "cmu_npybvh_example_75f: 75 frames" in out and "ik" in out
    png = tmp_path / "body_cmu_npybvh_example_75f.png"
    img = np.asarray(Image.open(png))
    assert img.shape[0] > 100 and img.std() > 10


def test_cli_body_arm_and_hand_clearance_skin_contact_and_self_contact_options(tmp_path, capsys):
    args = ["body", "--clip", "cmu_131_01_walk_3dsmax", "--max-frames", "40", "--out", str(tmp_path), "--no-png"]
    assert main(args) == 0
    turned = capsys.readouterr().out
    assert main(args + ["--arm-clearance", "0", "--no-hand-clearance"]) == 0
    exact = capsys.readouterr().out
    assert main(args + ["--arm-clearance", "0"]) == 0
    hands = capsys.readouterr().out
    # the walker's arms hang close to the body: by default they are turned out, with 0 they are copied
    assert float(turned.split("arm turn deg median ")[1].split(" max ")[1].split()[0]) > 1.0
    assert "arm turn deg median 0.0 max 0.0 " in exact
    # ... but for the hands: copied, they hang into the hips, and the hand clearance turns the arm out
    assert float(hands.split("arm turn deg median ")[1].split(" max ")[1].split()[0]) > 5.0
    with pytest.raises(SystemExit, match="--arm-clearance must be in"):
        main(args + ["--arm-clearance", "95"])
    # the walker's knees bend: by default the skins behind them meet, with --no-skin-contact they overlap
    moved = int(turned.split("skin contact: vertices moved median ")[1].split(" max ")[1].split()[0])
    assert moved > 20
    assert main(args + ["--no-skin-contact"]) == 0
    assert "skin contact: vertices moved median 0 max 0 " in capsys.readouterr().out
    assert main(args + ["--self-contact", "10"]) == 0
    out = capsys.readouterr().out
    assert "clothed skin inside another part of the body, vertices per frame (mean over 4 frames): torso" in out
    with pytest.raises(SystemExit, match="--self-contact must be 0"):
        main(args + ["--self-contact", "-1"])


def test_cli_reports_bad_clip(tmp_path, capsys):
    bad = tmp_path / "bad.bvh"
    bad.write_text("HIERARCHY\nROOT Hips\n{\n")
    rc = main(["body", "--clip", str(bad), "--out", str(tmp_path), "--no-png"])
    assert rc == 2
    assert "bad.bvh" in capsys.readouterr().err


def test_cli_cloth_close_up_snapshots_of_chosen_frames(tmp_path, capsys):
    rc = main(["cloth", "--outfit", "female_sportsuit01", "--clip", "cmu_npybvh_example_75f", "--max-frames", "6",
               "--frames", "2,5", "--close-up", "--out", str(tmp_path)])
    assert rc == 0
    assert ("cmu_npybvh_example_75f × female_sportsuit01 (female_sportsuit01.top jersey, female_sportsuit01.bottom "
            "jersey): 5 frames") in capsys.readouterr().out  # frame 0 is skipped; each garment's fabric
    img = np.asarray(Image.open(tmp_path / "cloth_cmu_npybvh_example_75f_female_sportsuit01_close.png"))
    assert img.shape[:2] == (800, 4 * 600)  # two frames, each from two sides
    assert img.std() > 10


def test_cli_cloth_rejects_bad_frames(tmp_path):
    with pytest.raises(SystemExit, match="frames 'two'"):
        main(["cloth", "--frames", "two", "--out", str(tmp_path), "--no-png"])


def test_showcase_frames_are_session_frame_numbers():
    from services.body_job import showcase_frames

    # jumping jacks at 60 Hz: the 120 Hz showcase frames halved, the converter T-pose skipped
    assert showcase_frames("cmu_13_29_jumping_jacks", 2, 1) == [1, 35, 100, 500, 1250, 1980, 2170]
    assert showcase_frames("cmu_13_29_jumping_jacks") == [0, 70, 200, 1000, 2500, 3960, 4340]
    assert showcase_frames("unknown", 1) == [0, 100, 200, 300]
