"""One model-folder layout: every shipped model and training run folder is found by one rule
(:func:`diffgns.models.model_dir`), older layouts still load, and a wrong path gets one clean
error naming what the folder lacks and what exists."""
from __future__ import annotations

import json
import shutil

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
