"""The Python package against the command line and against an independent
reader of its files: tiny simulated captures, made by the tests."""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import pathlib
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

import omniscan

REPO = pathlib.Path(__file__).resolve().parents[2]


def cli_binary() -> pathlib.Path:
    """The Rust command line, built by `cargo build --release -p omniscan`
    (`.ci/run`'s test command builds it)."""
    path = pathlib.Path(os.environ.get("OMNISCAN_BIN", REPO / "target/release/omniscan"))
    if not path.exists():
        subprocess.run(["cargo", "build", "--release", "-p", "omniscan"], cwd=REPO, check=True)
    return path


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(cli_binary()), *args], capture_output=True, text=True)


TINY = dict(object="builtin:remote", width=64, height=48, seed=5, supersample=1, wrist_angles=3, latitudes=2)


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> pathlib.Path:
    out = tmp_path_factory.mktemp("scan") / "capture"
    omniscan.simulate(out=out, **TINY)
    omniscan.mask(out)
    return out


def md5(path: pathlib.Path) -> str:
    return hashlib.md5(path.read_bytes()).hexdigest()


def read_ply_independently(path: pathlib.Path) -> dict:
    """A binary little-endian PLY's vertex columns, read with numpy alone."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    names, types = [], []
    count = None
    for line in data[:end].decode().splitlines():
        words = line.split()
        if words[:2] == ["element", "vertex"]:
            count = int(words[2])
        elif words and words[0] == "property":
            assert words[1] == "float", line
            names.append(words[2])
            types.append("<f4")
    table = np.frombuffer(data[end:], dtype=np.dtype(list(zip(names, types))), count=count)
    assert len(data) - end == table.nbytes, "bytes the header does not describe"
    return {name: table[name] for name in names}


def test_defaults_are_the_libraries_and_unknown_arguments_are_refused():
    train = omniscan.settings("train")
    assert train["steps"] > 0 and train["arm"] == "left" and train["backend"] == "auto"
    assert omniscan.settings("inspect")["threshold_mm"] == 4.5
    with pytest.raises(TypeError, match="unexpected keyword arguments \\['stepz'\\]"):
        omniscan.train("x", out="y.ply", stepz=3)
    with pytest.raises(omniscan.InputError, match="setting `steps`"):
        omniscan.train("x", out="y.ply", steps=-1)


def test_a_twin_made_through_python_is_byte_identical_to_the_clis(capture, tmp_path):
    settings = dict(steps=30, backend="cpu", downscale=1)
    report = omniscan.twin(capture, out=tmp_path / "py", **settings)
    out = run_cli(
        "twin", str(capture), "--out", str(tmp_path / "cli"), "--steps", "30", "--backend", "cpu", "--downscale", "1", "--json"
    )
    assert out.returncode == 0, out.stderr
    cli = json.loads(out.stdout)
    for name in ["left.ply", "right.ply", "twin.ply"]:
        assert md5(tmp_path / "py" / name) == md5(tmp_path / "cli" / name), name
    # The transform file also names its folder's models and its time.
    ours, theirs = (json.loads((tmp_path / d / "right_to_left.json").read_text()) for d in ["py", "cli"])
    for key in ["transform", "fitness", "inlier_rmse", "method", "correspondences"]:
        assert ours[key] == theirs[key], key
    assert report.stages.twin.report.splats == cli["stages"]["twin"]["report"]["splats"]
    assert report.to_dict()["stages"]["twin"]["report"]["test"] == cli["stages"]["twin"]["report"]["test"]


def test_splat_arrays_are_the_ply_files_contents(capture, tmp_path):
    model = tmp_path / "m.ply"
    report = omniscan.train(capture, out=model, steps=20, backend="cpu")
    splats = omniscan.read_splats(model)
    assert len(splats) == report.splats
    columns = read_ply_independently(model)
    np.testing.assert_array_equal(splats.means, np.stack([columns[k] for k in "xyz"], axis=1))
    np.testing.assert_array_equal(splats.scales, np.stack([columns[f"scale_{i}"] for i in range(3)], 1))
    np.testing.assert_array_equal(splats.quats, np.stack([columns[f"rot_{i}"] for i in range(4)], 1))
    np.testing.assert_array_equal(splats.opacities, columns["opacity"])
    np.testing.assert_array_equal(splats.sh[:, 0, :], np.stack([columns[f"f_dc_{i}"] for i in range(3)], 1))
    k = splats.sh.shape[1]
    for c in range(3):
        for j in range(1, k):
            np.testing.assert_array_equal(splats.sh[:, j, c], columns[f"f_rest_{c * (k - 1) + j - 1}"])

    # Edited arrays write and read back; a NaN is refused, naming the splat.
    splats.means[0] = [0.25, -0.5, 1.0]
    omniscan.write_splats(tmp_path / "edited.ply", splats)
    back = omniscan.read_splats(tmp_path / "edited.ply")
    np.testing.assert_array_equal(back.means, splats.means)
    np.testing.assert_array_equal(back.sh, splats.sh)
    splats.opacities[3] = np.nan
    with pytest.raises(omniscan.InputError, match="splat 3"):
        omniscan.write_splats(tmp_path / "nan.ply", splats)


def test_a_model_converts_and_shows_in_a_page(capture, tmp_path):
    model = tmp_path / "m.ply"
    omniscan.train(capture, out=model, steps=20, backend="cpu")
    report = omniscan.convert(model, out=tmp_path / "m.spz", spz_version=3)
    assert report.format == "SPZ" and report.splats == len(omniscan.read_splats(model))
    back = omniscan.read_splats(tmp_path / "m.spz")
    np.testing.assert_allclose(back.means, omniscan.read_splats(model).means, atol=2.5e-4)
    page = omniscan.view([model, tmp_path / "m.spz"], out=tmp_path / "v.html", names=["ply", "spz"])
    assert page.models == 2
    html = (tmp_path / "v.html").read_text()
    assert "omniscan-viewer-config" in html and ">spz</button>" in html
    with pytest.raises(omniscan.InputError, match="unknown model format"):
        omniscan.convert(model, out=tmp_path / "m.xyz")


def test_point_clouds_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    cloud = omniscan.PointCloud(rng.normal(size=(50, 3)), rng.random((50, 3)).astype(np.float32), None)
    omniscan.write_cloud(tmp_path / "c.ply", cloud)
    back = omniscan.read_cloud(tmp_path / "c.ply")
    np.testing.assert_allclose(back.points, cloud.points, rtol=1e-6)
    assert back.normals is None and back.colors.shape == (50, 3)


def test_errors_are_typed_and_name_the_file(tmp_path):
    with pytest.raises(omniscan.FileError) as missing:
        omniscan.read_splats(tmp_path / "missing.ply")
    assert "missing.ply" in str(missing.value) and isinstance(missing.value, OSError)
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    with pytest.raises(omniscan.InputError, match="bad.ply: not a 3DGS PLY"):
        omniscan.read_splats(tmp_path / "bad.ply")


def test_an_output_in_use_is_refused_naming_the_holder(capture, tmp_path):
    out = tmp_path / "busy"
    out.mkdir()
    with open(out / ".omniscan.lock", "w") as lock:
        lock.write("a test (process 1)")
        lock.flush()
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(omniscan.OutputInUse, match="in use by a test"):
            omniscan.twin(capture, out=out, steps=5)


def test_progress_reaches_python_and_the_gil_is_released(tmp_path):
    events = []

    class Recorder:
        def start(self, label, total, unit):
            events.append(("start", label, total, unit))

        def set(self, done):
            events.append(("set", done))

    ticks = []
    done = threading.Event()

    def tick():
        while not done.is_set():
            ticks.append(time.monotonic())
            time.sleep(0.005)

    ticker = threading.Thread(target=tick)
    ticker.start()
    try:
        omniscan.simulate(out=tmp_path / "cap", progress=Recorder(), **{**TINY, "width": 128, "height": 96})
    finally:
        done.set()
        ticker.join()
    starts = [e for e in events if e[0] == "start"]
    assert starts and starts[0][1] == "simulating" and starts[0][3] == "frames"
    assert [e for e in events if e[0] == "set"][-1] == ("set", starts[0][2])
    # Python ran while the simulator did: it holds no GIL.
    assert len(ticks) > 10


def test_the_omniscan_command_is_the_cli(capture):
    ours = subprocess.run(
        [sys.executable, "-m", "omniscan", "validate", str(capture), "--json"], capture_output=True, text=True
    )
    assert ours.returncode == 0, ours.stderr
    theirs = run_cli("validate", str(capture), "--json")
    assert json.loads(ours.stdout) == json.loads(theirs.stdout)
    refused = subprocess.run([sys.executable, "-m", "omniscan", "validate", "/nonexistent"], capture_output=True, text=True)
    assert refused.returncode == 1 and "no such file" in refused.stderr


def test_the_stubs_are_current():
    stubs = subprocess.run(
        [sys.executable, str(REPO / "scripts/python-stubs"), "--print"], capture_output=True, text=True, check=True
    )
    assert stubs.stdout == (REPO / "python/omniscan/__init__.pyi").read_text(), "run scripts/python-stubs"
