"""One model-folder layout: every shipped model and training run folder is found by one rule
(:func:`diffgns.models.model_dir`), older layouts still load, and a wrong path gets one clean
error naming what the folder lacks and what exists."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import jax
import numpy as np
import pytest

from diffgns.errors import InputError
from diffgns.models import ModelFolderError, model_dir, model_path, models_root, shipped_models


@pytest.mark.parametrize("name", shipped_models())
def test_every_shipped_model_is_a_model_folder(name):
    folder = model_dir(name)
    assert (folder / "params.msgpack").is_file()
    assert (folder / "config.json").is_file() or (folder / "model.json").is_file()
    if not name.startswith("message_net"):  # the layout: weights beside the card
        assert folder == models_root() / name
    assert model_dir(f"models/{name}") == folder  # the repository-relative spelling


def test_a_path_one_level_too_deep_finds_the_model():
    for name in ("gns_columns", "meshnet_cylinder"):
        assert model_dir(f"{name}/model") == model_dir(name) == models_root() / name
        assert model_dir(f"models/{name}/model") == models_root() / name
        assert model_path(models_root() / name / "model") == models_root() / name


@pytest.mark.slow  # ~15 s of network set-up
def test_the_meshgraphnet_loads_from_either_spelling_with_the_same_weights():
    from diffgns.mesh.train import load_model

    model, params, info = load_model("meshnet_cylinder")
    _, params_old, info_old = load_model("meshnet_cylinder/model")  # the earlier spelling
    assert info == info_old and info["kind"] == "meshgraphnet"
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(params_old)):
        assert np.array_equal(np.asarray(a), np.asarray(b))


def test_run_folders_and_the_old_layout_of_user_folders_load(tmp_path):
    from diffgns.graph.train_loop import load_model

    run = tmp_path / "run"
    shutil.copytree(model_dir("gns_small"), run / "model")  # what `diffgns train` writes
    ref_gns, ref, _ = load_model("gns_small")
    for path in (run, run / "model"):
        gns, params, info = load_model(path)
        assert gns.config == ref_gns.config
        for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(ref)):
            assert np.array_equal(np.asarray(a), np.asarray(b))


def test_a_wrong_model_path_is_one_clean_error_listing_what_exists(tmp_path):
    from diffgns.graph.train_loop import load_model
    from diffgns.mesh.train import load_model as load_mesh

    with pytest.raises(ModelFolderError, match=r"'gns_columns' has no modl; it contains "
                       r"MODEL_CARD\.md, .*config\.json"):
        load_model("models/gns_columns/modl")
    with pytest.raises(ModelFolderError, match="not an existing path .* shipped models: "
                       "gns_cg16, "):
        load_model(tmp_path / "missing")
    (tmp_path / "empty" / "logs").mkdir(parents=True)
    with pytest.raises(ModelFolderError, match=r"lacks params\.msgpack and config\.json "
                       r"\(particle GNS\) .*; it contains logs/"):
        load_model(tmp_path / "empty")
    with pytest.raises(ModelFolderError, match=r"its config\.json is a particle GNS\): it "
                       r"lacks model\.json"):
        load_mesh("gns_columns")
    # the command line reports it as invalid input (exit 2); old callers catch OSErrors
    e = pytest.raises(ModelFolderError, model_dir, tmp_path / "missing").value
    assert isinstance(e, InputError) and isinstance(e, FileNotFoundError)
    assert str(e).startswith("model: ") and "\n" not in str(e)


def test_package_data_globs_cover_every_shipped_weight_file():
    """pyproject's package-data patterns (relative to diffgns/models) match each shipped
    model's weights and configuration, so a wheel carries them."""
    import fnmatch

    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    root = models_root()
    pyproject = root.parents[2] / "pyproject.toml"
    if not pyproject.is_file():
        pytest.skip("not a source checkout")
    globs = tomllib.loads(pyproject.read_text())["tool"]["setuptools"]["package-data"][
        "diffgns.models"]
    for name in shipped_models():
        folder = model_dir(name)
        for f in ["params.msgpack", "config.json", "model.json"]:
            if (folder / f).is_file():
                rel = (folder / f).relative_to(root).as_posix()
                assert any(fnmatch.fnmatch(rel, g) and rel.count("/") == g.count("/")
                           for g in globs), rel
        assert json.loads(next(folder.glob("*.json")).read_text())


@pytest.mark.slow  # ~20 s each: network set-up and 32 frames on the sweep mesh
@pytest.mark.parametrize("name", ["meshnet_sweep", "meshnet_sweep_wide"])
def test_the_shipped_meshgraphnet_sheds_with_the_cfds_lift(name):
    """The shipped MeshGraphNet ``name`` loads by name and, from the CFD's frame 0 at
    held-out Re 165 (33 frames stored in float16, 2 shedding periods), its 32-frame rollout
    stays within 0.04 m/s RMS of the CFD, and the pressure lift of the rollout follows the
    CFD's (correlation > 0.95, peak-to-peak within 20%): the regression guard of its model
    card's Re 165 row."""
    from diffgns.interface import rollout_jit
    from diffgns.mesh.evaluate import graph_of, pressure_force_coefficients
    from diffgns.mesh.train import load_model

    d = np.load(Path(__file__).parent / "data" / "sweep_re165_frames.npz")
    traj = {k: d[k] for k in ("mesh_pos", "cells", "node_type", "on_cylinder")}
    traj["attrs"] = json.loads(str(d["attrs"]))
    traj["velocity"] = d["velocity"].astype(np.float32)
    pressure = d["pressure"].astype(np.float32)
    model, params, info = load_model(name)
    assert info["kind"] == "meshgraphnet" and model.config.latent == 64
    n, F = len(traj["mesh_pos"]), len(traj["velocity"])
    graph = graph_of(traj, info["padding"])
    v0 = np.zeros((info["padding"][0], 2), np.float32)
    v0[:n] = traj["velocity"][0]
    frames, _ = rollout_jit(model, params, model.init(graph, v0), n_frames=F - 1)
    v = np.asarray(frames.velocity)[:, :n]
    fluid = np.asarray(graph.predicted)[:n]
    rmse = np.sqrt(np.mean((v[-1, fluid] - traj["velocity"][-1, fluid]) ** 2))
    assert np.isfinite(v).all() and rmse < 0.04, rmse
    cl_cfd = pressure_force_coefficients(traj, pressure[1:])[1]
    cl = pressure_force_coefficients(traj, np.asarray(frames.pressure)[1:, :n])[1]
    assert np.corrcoef(cl, cl_cfd)[0, 1] > 0.95
    assert abs(np.ptp(cl) / np.ptp(cl_cfd) - 1) < 0.2, (np.ptp(cl), np.ptp(cl_cfd))
