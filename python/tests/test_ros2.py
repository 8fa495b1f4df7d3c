"""`omniscan.import_ros2` against a bag written by another implementation:
Foxglove's `mcap-ros2-support` (its CDR encoder works from the message
definitions in scripts/capture-to-ros2-bag). A simulated capture goes out
as a bag and comes back the same: frames per arm and phase, poses, pixels
and depth."""

import importlib.machinery
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

import omniscan
from omniscan.errors import InputError

pytest.importorskip("mcap_ros2", reason="needs mcap-ros2-support (the test extra)")
Image = pytest.importorskip("PIL.Image", reason="needs pillow (the test extra)")

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "capture-to-ros2-bag"


def bag_writer():
    loader = importlib.machinery.SourceFileLoader("capture_to_ros2_bag", str(SCRIPT))
    spec = importlib.util.spec_from_loader(loader.name, loader)
    module = importlib.util.module_from_spec(spec)
    loader.exec_module(module)
    return module


def pixels(path):
    return np.asarray(Image.open(path))


def test_a_bag_from_another_writer_imports_to_the_same_capture(tmp_path):
    sim = tmp_path / "sim"
    omniscan.simulate(out=sim, object="builtin:remote", width=96, height=72, wrist_angles=3, latitudes=2, supersample=1)
    bag = tmp_path / "scan.mcap"
    bag_writer().main(sim, bag)
    out = tmp_path / "imported"
    report = omniscan.import_ros2(bag, out=out)
    a = json.loads((sim / "capture.json").read_text())
    b = json.loads((out / "capture.json").read_text())
    assert report.left_frames + report.right_frames == len(a["frames"])
    assert report.skipped_images == 0
    for key in ("fx", "fy", "cx", "cy", "width", "height"):
        assert b["camera"][key] == pytest.approx(a["camera"][key], abs=1e-9)
    assert "distortion" not in b["camera"]
    for name in ("frames", "empty_frames"):
        assert len(a[name]) == len(b[name])
        for fa, fb in zip(a[name], b[name]):
            assert fa["arm"] == fb["arm"]
            assert np.abs(np.array(fa["gripper_to_world"]) - np.array(fb["gripper_to_world"])).max() < 1e-6
            assert (pixels(sim / fa["file_path"]) == pixels(out / fb["file_path"])).all()
            assert (pixels(sim / fa["depth_path"]) == pixels(out / fb["depth_path"])).all()
            assert fb["gripper_opening_m"] == pytest.approx(fa["gripper_opening_m"], abs=1e-12)
    for arm in ("left_gripper_to_world", "right_gripper_to_world"):
        assert np.abs(np.array(a["handover"][arm]) - np.array(b["handover"][arm])).max() < 1e-6

    # Asked for a topic the bag lacks, the import names it and writes nothing.
    with pytest.raises(InputError, match="no messages on /camera/rgb"):
        omniscan.import_ros2(bag, out=tmp_path / "again", image_topic="/camera/rgb")
    assert not (tmp_path / "again").exists()
