"""Tests of diffgns.io.figures: GIF animation, static plots and VTK output."""
from __future__ import annotations

import xml.etree.ElementTree as ET

import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

from diffgns.io import figures as viz
from diffgns.trajectory import FLUID, KINEMATIC, SAND, Trajectory

DT = 0.0025


def make_traj(n_frames: int = 5, n_particles: int = 12, seed: int = 0) -> Trajectory:
    rng = np.random.default_rng(seed)
    pos = rng.random((n_frames, n_particles, 2)).astype(np.float32) * np.float32(0.5)
    vel = rng.normal(size=(n_frames, n_particles, 2)).astype(np.float32)
    ptype = np.array([SAND, FLUID, KINEMATIC])[np.arange(n_particles) % 3].astype(np.int32)
    return Trajectory(positions=jnp.asarray(pos), velocities=jnp.asarray(vel),
                      particle_type=jnp.asarray(ptype),
                      material=jnp.asarray(rng.random(n_particles).astype(np.float32)),
                      frame_dt=DT, bounds=((0.0, 1.0), (0.0, 0.5)))


def gif_frames(path) -> list[np.ndarray]:
    with Image.open(path) as im:
        frames = []
        for k in range(im.n_frames):
            im.seek(k)
            frames.append(np.asarray(im.convert("RGB")))
    return frames


def test_animate_frame_count_and_panels(tmp_path):
    trajs = [make_traj(), make_traj(n_frames=3, seed=1)]  # the shorter one holds its last frame
    path = viz.animate(trajs, tmp_path / "out" / "anim.gif", titles=["mpm", "gns"], fps=10)
    assert path.exists()
    frames = gif_frames(path)
    assert len(frames) == 5
    height, width = frames[0].shape[:2]
    assert width > 1.5 * height  # two panels side by side
    assert not np.array_equal(frames[0], frames[1])  # time label / particles change


@pytest.mark.parametrize(("n_frames", "every", "expected"), [(7, 3, 3), (6, 2, 3), (4, 1, 4)])
def test_animate_every_and_speed_colouring(tmp_path, n_frames, every, expected):
    path = viz.animate(make_traj(n_frames=n_frames), tmp_path / "speed.gif", every=every,
                       color="speed", s=4.0)
    assert len(gif_frames(path)) == expected


def test_animate_rejects_bad_arguments(tmp_path):
    traj = make_traj()
    with pytest.raises(ValueError, match="titles"):
        viz.animate([traj, traj], tmp_path / "a.gif", titles=["one"])
    with pytest.raises(ValueError, match="color"):
        viz.animate(traj, tmp_path / "a.gif", color="pressure")
    with pytest.raises(ValueError, match="frame_dt"):
        viz.animate([traj, traj.replace(frame_dt=0.01)], tmp_path / "a.gif")


def test_plot_runout_and_deposits(tmp_path):
    t = np.linspace(0.0, 1.0, 20)
    runouts = [0.2 + 0.1 * t, 0.2 + 0.15 * t]
    out = viz.plot_runout(t, runouts, tmp_path / "runout.png", labels=["mpm", "gns"], L0=0.2)
    with Image.open(out) as im:
        assert im.format == "PNG" and im.size[0] > 100
    viz.plot_runout([t, t[:10]], [runouts[0], runouts[1][:10]], tmp_path / "r2.png")
    viz.plot_runout(t, np.stack(runouts), tmp_path / "r3.png")
    with pytest.raises(ValueError, match="labels"):
        viz.plot_runout(t, runouts, tmp_path / "r4.png", labels=["one"])
    with pytest.raises(ValueError, match="shape"):
        viz.plot_runout(t[:5], runouts, tmp_path / "r5.png")

    traj = make_traj()
    out = viz.plot_deposits([(traj.positions[-1], "mpm"), (np.asarray(traj.positions[0]), "gns")],
                            tmp_path / "deposits.png", traj.bounds)
    with Image.open(out) as im:
        assert im.format == "PNG"
    with pytest.raises(ValueError, match="bad"):
        viz.plot_deposits([(np.zeros((3, 3)), "bad")], tmp_path / "d.png", traj.bounds)


def _pixels_near(path, rgb, tol=40) -> int:
    with Image.open(path) as im:
        a = np.asarray(im.convert("RGB")).astype(int)
    return int((np.abs(a - np.asarray(rgb)).max(-1) < tol).sum())


def test_plot_runout_draws_labelled_reference_lines(tmp_path):
    """A reference (Lube's law) is a dashed line in the next colour of the cycle (C1 after
    one curve, orange): none without it, a horizontal run of it with it."""
    t = np.linspace(0.0, 1.0, 20)
    curve = 0.1 + 0.2 * t  # normalised 0 -> 2 with L0 = 0.1
    orange = (255, 127, 14)
    plain = viz.plot_runout(t, curve, tmp_path / "plain.png", labels=["deposit front"], L0=0.1)
    ref = viz.plot_runout(t, curve, tmp_path / "ref.png", labels=["deposit front"], L0=0.1,
                          references=[(1.5, "Lube et al. (2005): 1.50")],
                          ylabel="normalised runout", title="a = 2")
    assert _pixels_near(plain, orange) == 0
    assert _pixels_near(ref, orange) > 100
    with Image.open(ref) as im:
        rows = (np.abs(np.asarray(im.convert("RGB")).astype(int) - orange).max(-1) < 40)
    assert rows.sum(1).max() > 100  # a horizontal line, not a marker
    with pytest.raises(ValueError, match="reference"):
        viz.plot_runout(t, curve, tmp_path / "bad.png", references=[(np.nan, "Lube")])
    with pytest.raises(ValueError, match="reference"):
        viz.plot_runout(t, curve, tmp_path / "bad.png", references=[(1.0, "")])


def read_vtu(path) -> tuple[ET.Element, dict[str, np.ndarray]]:
    """Parse a pyevtk ``.vtu`` (XML header + raw appended binary) into its arrays."""
    raw = path.read_bytes()
    start = raw.index(b"<AppendedData")
    header = ET.fromstring(raw[:start] + b"</VTKFile>")  # the header alone is valid XML
    data_start = raw.index(b"_", start) + 1
    assert header.get("header_type") == "UInt64" and header.get("byte_order") == "LittleEndian"
    dtypes = {"Float32": "<f4", "Float64": "<f8", "Int32": "<i4", "Int64": "<i8", "UInt8": "u1"}
    arrays = {}
    for da in header.iter("DataArray"):
        offset = data_start + int(da.get("offset"))
        nbytes = int(np.frombuffer(raw, "<u8", count=1, offset=offset)[0])
        dtype = np.dtype(dtypes[da.get("type")])
        values = np.frombuffer(raw, dtype, count=nbytes // dtype.itemsize, offset=offset + 8)
        arrays[da.get("Name")] = values.reshape(-1, int(da.get("NumberOfComponents")))
    return header, arrays


def test_write_vtk_files_parse_and_match(tmp_path):
    traj = make_traj(n_frames=7, n_particles=9)
    paths = viz.write_vtk(traj, tmp_path / "vtk", prefix="col", every=3)
    frames = [0, 3, 6]
    assert [p.name for p in paths] == [f"col_{t:05d}.vtu" for t in frames] + ["col.pvd"]
    assert all(p.exists() for p in paths)

    for t, path in zip(frames, paths[:-1], strict=True):
        header, arrays = read_vtu(path)
        piece = header.find("./UnstructuredGrid/Piece")
        assert int(piece.get("NumberOfPoints")) == traj.n_particles
        names = {da.get("Name") for da in header.find(".//PointData").iter("DataArray")}
        assert names == {"velocity", "speed", "particle_type", "material"}
        pos, vel = np.asarray(traj.positions[t]), np.asarray(traj.velocities[t])
        np.testing.assert_array_equal(arrays["points"][:, :2], pos)
        np.testing.assert_array_equal(arrays["points"][:, 2], 0.0)
        np.testing.assert_array_equal(arrays["velocity"][:, :2], vel)
        np.testing.assert_array_equal(arrays["velocity"][:, 2], 0.0)
        np.testing.assert_allclose(arrays["speed"][:, 0], np.linalg.norm(vel, axis=1), rtol=1e-6)
        np.testing.assert_array_equal(arrays["particle_type"][:, 0], traj.particle_type)
        np.testing.assert_array_equal(arrays["material"][:, 0], traj.material)

    pvd = ET.parse(paths[-1]).getroot()
    assert pvd.get("type") == "Collection"
    datasets = pvd.findall("./Collection/DataSet")
    assert [d.get("file") for d in datasets] == [p.name for p in paths[:-1]]
    np.testing.assert_allclose([float(d.get("timestep")) for d in datasets],
                               [t * DT for t in frames])


def test_viz_does_not_touch_pyplot_state(tmp_path):
    """The module draws on private Agg canvases, so it leaves no pyplot figures open."""
    import matplotlib.pyplot as plt

    before = plt.get_fignums()
    viz.plot_deposits([(np.zeros((2, 2)), "a")], tmp_path / "d.png", ((0, 1), (0, 1)))
    viz.animate(make_traj(n_frames=2), tmp_path / "a.gif")
    assert plt.get_fignums() == before
