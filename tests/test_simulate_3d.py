"""``diffgns simulate`` on 3D scenes: TOML in; trajectory, ParaView files, a 3D animation
and a deposit figure out; 3D scene files refused with the field and the fix."""
import copy
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import h5py
import jax.numpy as jnp
import numpy as np
import pytest
import tomli_w
from PIL import Image

from diffgns import metrics
from diffgns.cli import main
from diffgns.io import figures as viz
from diffgns.io import figures3d as viz3d
from diffgns.io.dataset import DatasetWriter, load_dataset, read_metadata
from diffgns.trajectory import SAND, Trajectory
from test_viz import gif_frames, read_vtu

SCENE_DIR = Path(__file__).resolve().parents[1] / "scenes"

#: a 208-particle sand cylinder (R0 = 2 cells) on a Coulomb floor: compiles and runs in
#: about 10 s on 2 loaded cores
TINY = {
    "scene": {"domain": [[0.0, 0.24], [0.0, 0.08], [0.0, 0.24]], "dx": 0.02},
    "walls": {"bottom": {"kind": "friction", "mu": 0.5}},
    "bodies": [{"shape": {"type": "cylinder", "cx": 0.12, "cz": 0.12, "radius": 0.04,
                          "y0": 0.0, "y1": 0.04},
                "material": {"type": "sand", "friction_angle": 30.0}}],
}
FRAMES, VTK_EVERY, ANIM_EVERY = 8, 2, 4  # ANIM_EVERY: write_outputs' default


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """One CLI run of the tiny scene: (output folder, exit status, stdout)."""
    import contextlib
    import io

    tmp = tmp_path_factory.mktemp("sim3d")
    scene = tmp / "tiny.toml"
    scene.write_text(tomli_w.dumps(TINY))
    out = tmp / "out"
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        rc = main(["simulate", "--scene", str(scene), "--frames", str(FRAMES), "--vtk-every",
                   str(VTK_EVERY), "--out", str(out)])
    return out, rc, stdout.getvalue()


def test_writes_every_output(run):
    out, rc, _ = run
    assert rc == 0
    for f in ["animation.gif", "runout.png", "deposit.png", "trajectory.h5",
              "trajectory.metadata.json", "summary.json", "vtk/particles.pvd"]:
        assert (out / f).exists(), f


def test_trajectory_is_3d(run):
    out = run[0]
    (traj,) = load_dataset(out / "trajectory.h5")
    assert traj.positions.shape == (FRAMES + 1, 208, 3) == traj.velocities.shape
    assert traj.bounds == tuple(tuple(ax) for ax in TINY["scene"]["domain"])
    meta = read_metadata(out / "trajectory.h5")
    assert meta["dim"] == 3 and len(meta["vel_std"]) == 3 and len(meta["bounds"]) == 3
    x = np.asarray(traj.positions)
    assert x[-1, :, 1].mean() < x[0, :, 1].mean()  # the column slumps


def test_vtk_holds_the_trajectory(run):
    out = run[0]
    with h5py.File(out / "trajectory.h5") as f:
        pos, vel = f["00000/position"][()], f["00000/velocity"][()]
        ptype = f["00000/particle_type"][()]
    frames = list(range(0, FRAMES + 1, VTK_EVERY))
    vtus = [out / "vtk" / f"particles_{t:05d}.vtu" for t in frames]
    pvd = ET.parse(out / "vtk" / "particles.pvd").getroot()
    datasets = pvd.findall("./Collection/DataSet")
    assert [d.get("file") for d in datasets] == [p.name for p in vtus]
    dt = read_metadata(out / "trajectory.h5")["dt"]
    assert dt == pytest.approx(2.5e-3)  # the scene's default frame dt, s
    np.testing.assert_allclose([float(d.get("timestep")) for d in datasets],
                               [t * dt for t in frames])
    header, arrays = read_vtu(vtus[-1])
    assert int(header.find("./UnstructuredGrid/Piece").get("NumberOfPoints")) == 208
    assert arrays["points"].shape == (208, 3)
    np.testing.assert_array_equal(arrays["points"], pos[-1])  # the final positions, z kept
    np.testing.assert_array_equal(arrays["velocity"], vel[-1])
    np.testing.assert_allclose(arrays["speed"][:, 0], np.linalg.norm(vel[-1], axis=1),
                               rtol=1e-6)
    np.testing.assert_array_equal(arrays["particle_type"][:, 0], ptype)
    assert "material" in arrays
    assert np.ptp(arrays["points"][:, 2]) > 0.05  # a real depth, not a 2D slice


def test_animation_and_deposit_figure(run):
    out = run[0]
    frames = gif_frames(out / "animation.gif")
    assert len(frames) == len(range(0, FRAMES + 1, ANIM_EVERY))
    assert not np.array_equal(frames[0], frames[-1])
    with Image.open(out / "deposit.png") as im:
        w, h = im.size
    assert w > 1.5 * h  # top view and radial profile side by side


def test_summary_in_3d_terms_and_clamps_printed(run):
    out, _, stdout = run
    s = json.loads((out / "summary.json").read_text())
    printed = json.loads(stdout[stdout.index("{"):stdout.rindex("}") + 1])
    assert printed == {k: v for k, v in s.items() if k != "files"}
    assert set(s["runout_definitions"]) == {"final_runout_radius_m", "deposit_front_radius_m"}
    assert s["axis_xz_m"] == [0.12, 0.12] and s["initial_radius_m"] == 0.04
    assert s["aspect_ratio"] == 1.0 and s["normalised_runout_lube2004"] == pytest.approx(1.24)
    # outermost particles start a quarter cell inside R0 = 0.04 m and spread outwards
    assert 0.035 < s["final_runout_radius_m"] < 0.12
    assert 0 < s["deposit_front_radius_m"] <= s["final_runout_radius_m"] + 0.02
    assert s["normalised_runout_front"] == pytest.approx(
        (s["deposit_front_radius_m"] - 0.04) / 0.04)
    assert 0 < s["deposit_height_m"] < 0.04
    assert {"clamped_positions", "clamped_frames", "first_clamped_frame",
            "max_clamp_shift_m"} <= set(s)
    assert s["frames"] == FRAMES + 1 and s["particles"] == 208


# ------------------------------------------------------------------ the shipped example
def test_shipped_example_is_the_builders_axisymmetric_column():
    from diffgns.scene.builders3d import axisymmetric_column
    from diffgns.scene.files import load_scene

    scene = load_scene(SCENE_DIR / "axisymmetric_column_3d.toml")
    assert scene == axisymmetric_column()
    assert scene.dim == 3 and scene.n_particles < 4000


@pytest.mark.slow  # ~3 min on 2 loaded cores (160 frames took 247 s, 2026-12-03)
def test_shipped_example_collapses_axisymmetrically(tmp_path):
    out = tmp_path / "axi"
    assert main(["simulate", "--scene", str(SCENE_DIR / "axisymmetric_column_3d.toml"),
                 "--frames", "120", "--vtk-every", "40", "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["clamped_positions"] == 0
    assert s["normalised_runout_front"] > 0.3  # measured 0.6 (Lube et al.: 1.24; issue 24)
    (traj,) = load_dataset(out / "trajectory.h5")
    assert np.abs(np.asarray(traj.velocities[-1])).max() < 0.05  # at rest
    x = np.asarray(traj.positions[-1])
    d = x[:, [0, 2]] - np.asarray(s["axis_xz_m"])
    r, th = np.hypot(d[:, 0], d[:, 1]), np.arctan2(d[:, 1], d[:, 0])
    sectors = [np.percentile(r[(th >= lo) & (th < lo + np.pi / 2)], 99)
               for lo in (-np.pi, -np.pi / 2, 0.0, np.pi / 2)]
    assert (max(sectors) - min(sectors)) / np.mean(sectors) < 0.1


# ------------------------------------------------------------------ scene files refused
def _edit(**changes):
    d = copy.deepcopy(TINY)
    for where, value in changes.items():
        *path, key = where.split("__")
        node = d
        for p in path:
            node = node[int(p)] if p.isdigit() else node[p]
        if value is None:
            del node[key]
        else:
            node[key] = value
    return d


_RECT = {"type": "rectangle", "x0": 0.0, "y0": 0.0, "x1": 0.1, "y1": 0.04}
_DOMAIN_2D = [[0.0, 0.24], [0.0, 0.08]]


@pytest.mark.parametrize("changes,field,fix", [
    (dict(scene__gravity=[0.0, -9.81]), "[scene].gravity", "[gx, gy, gz]"),
    (dict(bodies__0__velocity=[0.1, 0.0]), "[[bodies]][0].velocity", "[vx, vy, vz]"),
    (dict(bodies__0__shape=_RECT), "bodies[0]", "Box/Cylinder in 3D"),
    (dict(scene__domain=_DOMAIN_2D), "bodies[0]", "Rectangle/Polygon in 2D"),
    (dict(scene__domain=_DOMAIN_2D, bodies__0__shape=_RECT,
          walls__front={"kind": "sticky"}), "[walls]", "allowed"),
    (dict(bodies__0__particles_per_cell=4), "particles_per_cell", "perfect cube"),
    (dict(bodies__0__shape__radius=None), "[[bodies]][0].shape", "missing ['radius']"),
    (dict(bodies__0__shape__cx=0.22), "bodies[0]", "move or shrink the body"),
    (dict(bodies__0__shape={"type": "sphere"}), "[[bodies]][0].shape.type", "'cylinder'"),
    (dict(obstacles=[{"x0": 0.0, "y0": 0.0, "x1": 0.02, "y1": 0.02}]), "[[obstacles]][0]",
     "missing ['z0', 'z1']"),
    (dict(scene__domain=[[0.0, 0.24], [0.0, 0.08], [0.24, 0.0]]), "domain along z",
     "max > min"),
])
def test_bad_3d_scene_file_names_the_field_and_the_fix(tmp_path, capsys, changes, field, fix):
    path = tmp_path / "bad.toml"
    path.write_text(tomli_w.dumps(_edit(**changes)))
    out = tmp_path / "o"
    assert main(["simulate", "--scene", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith(f"diffgns: error: --scene {path}: ")
    assert field in err and fix in err, err
    assert "velocity" not in err or "velocity" in str(changes)  # no misleading field
    assert not out.exists()


# ------------------------------------------------------------------ figures and files
def _traj3d(n_frames=5, n=30, seed=0):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0.0, 0.2, (n_frames, n, 3)).astype(np.float32)
    return Trajectory(positions=jnp.asarray(pos),
                      velocities=jnp.asarray(rng.normal(size=pos.shape).astype(np.float32)),
                      particle_type=jnp.full(n, SAND, jnp.int32), material=jnp.zeros(n),
                      frame_dt=0.01, bounds=((0.0, 0.2), (0.0, 0.1), (0.0, 0.2)))


@pytest.mark.parametrize("n_frames,every,color,expected", [(5, 1, "type", 5),
                                                            (7, 3, "speed", 3)])
def test_animate3d_frames_and_panels(tmp_path, n_frames, every, color, expected):
    path = viz3d.animate3d(_traj3d(n_frames), tmp_path / "a.gif", every=every, color=color)
    frames = gif_frames(path)
    assert len(frames) == expected and not np.array_equal(frames[0], frames[1])
    two = viz3d.animate3d([_traj3d(3), _traj3d(2, seed=1)], tmp_path / "b.gif",
                          titles=["mpm", "other"])
    assert len(gif_frames(two)) == 3


def test_animations_refuse_the_wrong_dimension(tmp_path):
    flat = Trajectory(positions=jnp.zeros((2, 3, 2)), velocities=jnp.zeros((2, 3, 2)),
                      particle_type=jnp.zeros(3, jnp.int32), material=jnp.zeros(3))
    with pytest.raises(ValueError, match="mix dimensions"):
        viz.animate([flat, _traj3d()], tmp_path / "a.gif")
    with pytest.raises(ValueError, match="mix dimensions"):
        viz3d.animate3d([_traj3d(), flat], tmp_path / "a.gif")
    with pytest.raises(ValueError, match="3D trajectories"):
        viz3d.animate3d(flat, tmp_path / "a.gif")
    with pytest.raises(ValueError, match="animate3d"):
        viz.animate(_traj3d(), tmp_path / "a.gif")


def test_height_map_and_radial_distance():
    x = np.array([[0.01, 0.03, 0.01], [0.015, 0.05, 0.005], [0.19, 0.02, 0.11]])
    xe, ze, h = viz3d.height_map(x, ((0.0, 0.2), (0.0, 0.1), (0.0, 0.2)), 0.02)
    assert h.shape == (10, 10) and len(xe) == len(ze) == 11
    assert h[0, 0] == pytest.approx(0.05) and h[9, 5] == pytest.approx(0.02)
    assert np.isnan(h).sum() == 98
    np.testing.assert_allclose(np.asarray(metrics.radial_distance(x, (0.01, 0.01)))[:2],
                               [0.0, np.hypot(0.005, 0.005)], atol=1e-7)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        viz3d.plot_deposit3d(x[:, :2], x, "unused.png", ((0, 1),) * 3, 0.02, (0.0, 0.0))


def test_dataset_round_trip_3d_and_refuses_mixed_dimensions(tmp_path):
    import dataclasses

    boxes = ((0.05, 0.0, 0.05, 0.08, 0.02, 0.09), (0.1, 0.0, 0.1, 0.12, 0.03, 0.15))
    t = dataclasses.replace(_traj3d(), obstacles=boxes)  # 3D boxes: 6 numbers each
    with DatasetWriter(tmp_path / "d.h5") as w:
        w.write("00000", t)
        meta = w.finalize(connectivity_radius=0.02)
    assert meta["dim"] == 3 and np.shape(meta["bounds"]) == (3, 2)
    (back,) = load_dataset(tmp_path / "d.h5")
    np.testing.assert_array_equal(np.asarray(back.positions), np.asarray(t.positions))
    assert back.bounds == t.bounds and back.obstacles == boxes
    flat = Trajectory(positions=jnp.zeros((3, 4, 2)), velocities=jnp.zeros((3, 4, 2)),
                      particle_type=jnp.zeros(4, jnp.int32), material=jnp.zeros(4),
                      frame_dt=t.frame_dt)
    with DatasetWriter(tmp_path / "d.h5") as w:
        w.write("00001", flat)
        with pytest.raises(ValueError, match="mix dimensions"):
            w.finalize(connectivity_radius=0.02)
