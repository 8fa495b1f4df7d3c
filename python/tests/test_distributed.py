"""omniscan.distributed on a real Ray cluster on loopback (a head and a
worker node, one fake GPU each, so one-GPU-per-task scheduling is
exercised) with outputs on a local S3 server (moto): every twin committed
exactly once and byte-identical to the sequential CPU run, a worker killed
mid-run retried and resumed, a bad capture reported without stopping the
others, and a rerun that commits nothing. Needs the `distributed` extra and
moto's server (`.ci/run` installs both)."""

from __future__ import annotations

import hashlib
import json
import os
import pathlib
import signal
import socket
import subprocess
import sys
import time

import pytest

ray = pytest.importorskip("ray", reason="needs the distributed extra: pip install '.[distributed]'")
boto3 = pytest.importorskip("boto3")
pytest.importorskip("moto", reason="needs moto's S3 server: pip install 'moto[server]'")

from test_api import TINY, cli_binary  # noqa: E402

import omniscan  # noqa: E402

BIN = pathlib.Path(sys.executable).parent
STEPS = "120"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(check, seconds: float, what: str):
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        value = check()
        if value:
            return value
        time.sleep(0.1)
    raise TimeoutError(what)


@pytest.fixture(scope="module")
def s3(tmp_path_factory):
    """A local S3 server; its address in the environment the cluster inherits."""
    port = free_port()
    log = open(tmp_path_factory.mktemp("moto") / "moto.log", "w")
    server = subprocess.Popen([sys.executable, "-m", "moto.server", "-p", str(port)], stdout=log, stderr=log)
    env = {
        "AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}",
        "AWS_ACCESS_KEY_ID": "test",
        "AWS_SECRET_ACCESS_KEY": "test",
        "AWS_DEFAULT_REGION": "us-east-1",
    }
    os.environ.update(env)
    client = boto3.client("s3")
    wait_for(lambda: _reachable(client), 30, "moto's S3 server did not start")
    client.create_bucket(Bucket="scans")
    yield client
    server.terminate()
    server.wait()


def _reachable(client) -> bool:
    try:
        client.list_buckets()
        return True
    except Exception:
        return False


@pytest.fixture(scope="module")
def cluster(s3, tmp_path_factory):
    """A head and a worker node on 127.0.0.2, one fake GPU each."""
    port = free_port()
    address = f"127.0.0.2:{port}"
    # Ray 2.60 heads require a token; every node and the driver share it.
    os.environ.update({"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": os.urandom(32).hex()})
    env = {**os.environ, "OMNISCAN_SYNC_SECONDS": "0.3", "RAY_USAGE_STATS_ENABLED": "0"}
    common = ["--node-ip-address", "127.0.0.2", "--num-cpus", "1", "--num-gpus", "1", "--disable-usage-stats"]
    subprocess.run(
        [str(BIN / "ray"), "start", "--head", "--port", str(port), "--include-dashboard", "false", *common],
        env=env, check=True, capture_output=True,
    )
    try:
        subprocess.run([str(BIN / "ray"), "start", "--address", address, *common], env=env, check=True, capture_output=True)
        yield address
    finally:
        subprocess.run([str(BIN / "ray"), "stop", "--force"], capture_output=True)


@pytest.fixture(scope="module")
def captures(s3, tmp_path_factory):
    """Three tiny captures (one local, two on S3) and a broken one."""
    root = tmp_path_factory.mktemp("captures")
    made = []
    for seed in (1, 2, 3):
        path = root / f"part{seed}"
        omniscan.simulate(out=path, **{**TINY, "seed": seed})
        omniscan.mask(path)
        made.append(path)
    for path in made[1:]:
        for f in path.rglob("*"):
            if f.is_file() and not f.name.endswith(".lock"):
                s3.upload_file(str(f), "scans", f"captures/{path.name}/{f.relative_to(path).as_posix()}")
    broken = root / "broken"
    broken.mkdir()
    (broken / "capture.json").write_text('{"version": 1}')
    return {
        "local": [made[0], broken],
        "uris": [str(made[0]), "s3://scans/captures/part2", "s3://scans/captures/part3", str(broken)],
        "paths": made,
    }


def driver(address: str, uris, out: str, *extra: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "omniscan.distributed", "twin", *uris, "--out", out, "--address", address,
         "--gpus-per-task", "1", "--steps", STEPS, "--backend", "cpu", "--json", *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )


def omniscan_run_of(name: str):
    """The pid of the `omniscan twin` process working on `name`, and of its parent."""
    for proc in pathlib.Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            argv = (proc / "cmdline").read_bytes().split(b"\0")
            stat = (proc / "stat").read_text()
        except OSError:
            continue
        words = [a.decode(errors="replace") for a in argv]
        # `omniscan twin CAPTURE`: the package's command or the binary, not the driver.
        command = any(
            (w == "omniscan" or w.endswith("/omniscan")) and words[i + 1 : i + 2] == ["twin"]
            for i, w in enumerate(words)
        )
        if command and any(w.endswith(f"/{name}") for w in words):
            parent = int(stat.rsplit(")", 1)[1].split()[1])
            return int(proc.name), parent
    return None


def md5(data: bytes) -> str:
    return hashlib.md5(data).hexdigest()


def test_a_batch_on_ray_survives_a_killed_worker_and_commits_each_twin_once(s3, cluster, captures, tmp_path):
    run = driver(cluster, captures["uris"], "s3://scans/twins")
    # Kill the worker running part2 once its left model is done and synced
    # where a retry finds it: the right stage's record, written as that
    # stage starts, comes after the left one's final record.
    wait_for(
        lambda: s3.list_objects_v2(Bucket="scans", Prefix="twins/.work/part2/right.record.json").get("KeyCount"),
        180,
        "part2's right stage never reached S3",
    )
    pids = wait_for(lambda: omniscan_run_of("part2"), 60, "no omniscan run of part2")
    os.kill(pids[1], signal.SIGKILL)
    stdout, stderr = run.communicate(timeout=600)
    assert run.returncode == 1, stderr  # the broken capture failed
    results = {r["name"]: r for r in json.loads(stdout)}
    assert results["broken"]["status"] == "failed" and results["broken"]["attempts"] == 1
    assert "capture.json" in results["broken"]["error"]
    for name in ("part1", "part2", "part3"):
        assert results[name]["status"] == "committed", results[name]
        assert results[name]["psnr"] > 15
    assert results["part2"]["attempts"] == 2, results["part2"]
    # The retry went on from what the killed attempt had synced: its left
    # model was reused, not trained again.
    report = json.loads(s3.get_object(Bucket="scans", Key="twins/part2/report.json")["Body"].read())
    assert report["stages"]["left"]["status"] == "reused", report["stages"]["left"]["status"]
    assert results["part1"]["attempts"] == 1 and results["part3"]["attempts"] == 1

    # Byte-identical to the sequential CPU run of the command line.
    for path in captures["paths"]:
        local = tmp_path / path.name
        done = subprocess.run(
            [str(cli_binary()), "twin", str(path), "--out", str(local), "--steps", STEPS, "--backend", "cpu"],
            capture_output=True, text=True,
        )
        assert done.returncode == 0, done.stderr
        for model in ("left.ply", "right.ply", "twin.ply"):
            remote = s3.get_object(Bucket="scans", Key=f"twins/{path.name}/{model}")["Body"].read()
            assert md5(remote) == md5((local / model).read_bytes()), (path.name, model)

    # A rerun commits nothing: every committed object is skipped.
    before = {o["Key"]: o["LastModified"] for o in s3.list_objects_v2(Bucket="scans", Prefix="twins/")["Contents"]}
    again = driver(cluster, captures["uris"][:3], "s3://scans/twins")
    stdout, stderr = again.communicate(timeout=300)
    assert again.returncode == 0, stderr
    assert {r["status"] for r in json.loads(stdout)} == {"skipped"}
    after = {o["Key"]: o["LastModified"] for o in s3.list_objects_v2(Bucket="scans", Prefix="twins/")["Contents"]}
    assert after == before


def test_a_shared_filesystem_commits_by_rename(cluster, captures, tmp_path):
    out = tmp_path / "twins"
    run = driver(cluster, [str(captures["paths"][0])], str(out))
    stdout, stderr = run.communicate(timeout=300)
    assert run.returncode == 0, stderr
    assert json.loads(stdout)[0]["status"] == "committed"
    committed = out / captures["paths"][0].name
    assert (committed / "report.json").is_file() and (committed / "twin.ply").is_file()
    assert not (out / ".work" / captures["paths"][0].name).exists(), "the work folder was renamed into place"
