"""The asset a twin becomes, loaded by a consumer: MuJoCo (the `mujoco`
wheel) reads the written MJCF and URDF; dropped onto a plane from 10 cm,
the object comes to rest on it with the mass and inertia written.

The twin is a splat model of an L-shaped block built here (two boxes), so
the test needs no training."""

import json
import math

import numpy as np
import pytest

import omniscan

mujoco = pytest.importorskip("mujoco", reason="needs the mujoco wheel (.ci/run installs it)")

SPACING = 0.0005


def face_splats(lo, hi):
    """Flat, opaque splats SPACING apart on the faces of the box lo..hi (metres)."""
    means, scales = [], []
    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3
        for side in (lo[axis], hi[axis]):
            us = np.arange(lo[u], hi[u] + 1e-9, SPACING)
            vs = np.arange(lo[v], hi[v] + 1e-9, SPACING)
            gu, gv = np.meshgrid(us, vs, indexing="ij")
            p = np.zeros((gu.size, 3))
            p[:, axis] = side
            p[:, u] = gu.ravel()
            p[:, v] = gv.ravel()
            s = np.full((gu.size, 3), math.log(SPACING))
            s[:, axis] = math.log(SPACING / 10)
            means.append(p)
            scales.append(s)
    return np.concatenate(means), np.concatenate(scales)


def l_block(path):
    """A 60 x 40 x 20 mm L (two boxes; their shared faces fuse away inside)."""
    parts = [face_splats((0, 0, 0), (0.06, 0.02, 0.02)), face_splats((0, 0, 0), (0.02, 0.04, 0.02))]
    means = np.concatenate([m for m, _ in parts]).astype(np.float32)
    scales = np.concatenate([s for _, s in parts]).astype(np.float32)
    n = len(means)
    colour = np.array([0.8, 0.5, 0.2])
    sh = ((colour - 0.5) / 0.28209479177387814).reshape(1, 1, 3).repeat(n, axis=0).astype(np.float32)
    model = omniscan.Splats(
        means=means,
        scales=scales,
        quats=np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1)),
        opacities=np.full(n, 4.0, np.float32),
        sh=sh,
    )
    omniscan.write_splats(path, model)
    # The solid's volume and mass at 1000 kg/m³.
    volume = 0.06 * 0.02 * 0.02 + 0.02 * 0.02 * 0.02
    return volume


@pytest.fixture(scope="module")
def asset(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("asset")
    volume = l_block(tmp / "block.ply")
    # A clean model: no inside vote (it would move the faces out by up to
    # three voxels, docs/mesh.md), so the volume is the block's.
    report = omniscan.asset(
        tmp / "block.ply", out=tmp / "asset", faces=3000, views=32, view_px=200, density_kg_m3=1000.0, inside_vote=2.0
    )
    return tmp / "asset", report, volume


def drop(model):
    """Drops the body from 10 cm above a floor for 2 s; returns the data."""
    data = mujoco.MjData(model)
    mujoco.mj_resetData(model, data)
    data.qpos[2] = 0.10
    for _ in range(int(2.0 / model.opt.timestep)):
        mujoco.mj_step(model, data)
    return data


def with_floor(spec):
    spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[1, 1, 0.1], pos=[0, 0, -0.05])
    return spec.compile()


def lowest_collision_point(model, data):
    """The lowest vertex of any collision mesh, world z."""
    lowest = math.inf
    for g in range(model.ngeom):
        if model.geom_type[g] != mujoco.mjtGeom.mjGEOM_MESH or model.geom_contype[g] == 0:
            continue
        m = model.geom_dataid[g]
        start, count = model.mesh_vertadr[m], model.mesh_vertnum[m]
        local = model.mesh_vert[start : start + count]
        world = local @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g]
        lowest = min(lowest, world[:, 2].min())
    return lowest


def test_the_report_and_files_are_complete(asset):
    out, report, volume = asset
    mass = report["mass"]
    assert mass["mass_kg"] == pytest.approx(1000.0 * volume, rel=0.05)
    assert report["mesh"]["topology"]["boundary_edges"] == 0
    assert len(report["collision_meshes"]) >= 2, "an L needs more than one convex piece"
    assert json.loads((out / "asset.json").read_text())["mass"]["mass_kg"] == mass["mass_kg"]
    for f in ("block.obj", "block.mtl", "block.png", "block.ply", "block.glb", "block.urdf", "block.xml"):
        assert (out / f).stat().st_size > 0, f


def test_mjcf_loads_and_the_object_comes_to_rest_on_a_plane(asset):
    out, report, _ = asset
    spec = mujoco.MjSpec.from_file(str(out / "block.xml"))
    model = with_floor(spec)
    body = model.body("block")
    mass = report["mass"]
    assert body.mass[0] == pytest.approx(mass["mass_kg"], rel=1e-6)
    assert sorted(body.inertia) == pytest.approx(sorted(mass["principal_inertia_kg_m2"]), rel=1e-4)
    data = drop(model)
    assert np.all(np.isfinite(data.qpos)), "the simulation exploded"
    assert np.linalg.norm(data.qvel[:3]) < 1e-3, f"still moving: {data.qvel}"
    # At rest on the floor (z = -0.05): touching it, less than 1 mm into it.
    penetration = -min((data.contact[i].dist for i in range(data.ncon)), default=0.0)
    assert data.ncon > 0
    assert penetration < 0.001, f"{penetration * 1000:.2f} mm into the floor"
    assert lowest_collision_point(model, data) == pytest.approx(-0.05, abs=0.0015)


def test_urdf_loads_with_the_written_inertia(asset):
    out, report, _ = asset
    spec = mujoco.MjSpec.from_file(str(out / "block.urdf"))
    # MuJoCo fixes a URDF's root link to the world: free it to drop it.
    spec.worldbody.first_body().add_freejoint()
    model = with_floor(spec)
    body = model.body("block")
    assert body.mass[0] == pytest.approx(report["mass"]["mass_kg"], rel=1e-6)
    assert sorted(body.inertia) == pytest.approx(sorted(report["mass"]["principal_inertia_kg_m2"]), rel=1e-4)
    data = drop(model)
    assert np.all(np.isfinite(data.qpos))
    assert np.linalg.norm(data.qvel[:3]) < 1e-3
    assert lowest_collision_point(model, data) == pytest.approx(-0.05, abs=0.0015)
