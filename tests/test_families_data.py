"""The general granular dataset (issue 21): ``diffgns dataset --kind granular`` writes MPM
trajectories of random family scenes with their obstacles, family and description, resumes
and extends by key, refuses another recipe, and refuses bad families before any JAX work."""
from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from diffgns.cli import main
from diffgns.errors import InputError
from diffgns.io.dataset import load_dataset, read_metadata
from diffgns.io.families_data import (
    generate_families,
    read_families,
    read_obstacles,
    read_ranges,
)
from diffgns.scene.families import random_sample
from diffgns.scene.recipes import family_plan

FAMS = ["obstacles", "columns"]


@pytest.mark.slow  # three MPM compilations (~70 s beside other jobs)
def test_granular_dataset_writes_resumes_and_extends(tmp_path):
    out = tmp_path / "g.h5"
    generate_families(out, FAMS, 2, 3, seed=4, progress=False)
    assert out.exists() and not out.with_name("g.h5.partial").exists()
    with h5py.File(out, "r") as f:
        stamp = float(f["00000"].attrs["mpm_seconds"])
    plan = family_plan(FAMS, 2, 4)
    assert read_families(out) == {"00000": "obstacles", "00001": "columns"}
    for key, (family, s) in zip(("00000", "00001"), plan):
        scene, desc = random_sample(family, s)
        np.testing.assert_array_equal(read_obstacles(out, key),
                                      np.asarray(desc["obstacles"]).reshape(-1, 4))
        with h5py.File(out, "r") as f:
            assert json.loads(f[key].attrs["description"]) == desc
            assert f[key]["position"].shape == (4, scene.n_particles, 2)
            np.testing.assert_allclose(f[key]["position"][0], scene.particles()["x"], atol=1e-6)
    assert len(read_obstacles(out, "00000")) >= 1 and read_obstacles(out, "00001").shape == (0, 4)
    meta = read_metadata(out)
    assert meta["kind"] == "granular" and meta["family_counts"] == {"obstacles": 1, "columns": 1}
    # a larger n extends the file: the first two trajectories are kept, not recomputed
    generate_families(out, FAMS, 3, 3, seed=4, progress=False)
    with h5py.File(out, "r") as f:
        assert float(f["00000"].attrs["mpm_seconds"]) == stamp and len(f) == 3
    trajs = load_dataset(out)
    assert all(np.isfinite(np.asarray(t.positions)).all() for t in trajs)
    with pytest.raises(InputError, match="families"):  # another recipe is refused
        generate_families(out, ["squares"], 3, 3, seed=4, progress=False)


@pytest.mark.slow  # two MPM compilations (~60 s beside other jobs)
def test_granular_shards_merge_into_the_one_process_layout(tmp_path):
    """--shard 0/2 and 1/2 (one per core) merged: every sample once, with its family and
    obstacles as drawn."""
    from diffgns.io.shards import merge_shards, shards_of
    from diffgns.shard import Shard

    out = tmp_path / "g.h5"
    for i in (0, 1):
        generate_families(out, FAMS, 2, 3, seed=5, progress=False, shard=Shard(i, 2))
    merge_shards(shards_of(out, 2), out)
    assert read_families(out) == {"00000": "obstacles", "00001": "columns"}
    for key, (family, s) in zip(("00000", "00001"), family_plan(FAMS, 2, 5)):
        desc = random_sample(family, s)[1]
        np.testing.assert_array_equal(read_obstacles(out, key),
                                      np.asarray(desc["obstacles"]).reshape(-1, 4))
    assert read_metadata(out)["family_counts"] == {"obstacles": 1, "columns": 1}


@pytest.mark.parametrize("families", [["boulders"], ["columns", "sand"]])
def test_cli_refuses_unknown_family(tmp_path, capsys, families):
    out = tmp_path / "x.h5"
    assert main(["dataset", "--kind", "granular", "--families", *families, "--out",
                 str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("diffgns: error: --families") and len(err.splitlines()) == 1
    assert not out.exists()


@pytest.mark.parametrize("boxes, field, words", [
    (["1.41x0.35"], "--boxes", "not a whole number"),
    (["1.4"], "--boxes", "LENGTHxHEIGHT"),
    (["0x0.35"], "--boxes", "> 0"),
])
def test_cli_refuses_a_bad_box(tmp_path, capsys, boxes, field, words):
    out = tmp_path / "x.h5"
    assert main(["dataset", "--kind", "granular", "--boxes", *boxes, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"diffgns: error: {field}") and words in err
    assert not out.exists()


@pytest.mark.parametrize("option, value", [("--young-modulus", "0"),
                                           ("--young-modulus", "-2e7"),
                                           ("--young-modulus", "nan"), ("--flip", "1.5"),
                                           ("--flip", "-0.1")])
def test_cli_refuses_a_bad_young_modulus_or_flip(tmp_path, capsys, option, value):
    out = tmp_path / "x.h5"
    assert main(["dataset", "--kind", "granular", option, value, "--out", str(out)]) == 2
    assert option in capsys.readouterr().err
    assert not out.exists()


def test_the_young_modulus_is_part_of_the_recipe_and_redraws_with_it(tmp_path):
    """A set made with --young-modulus records E in its recipe's ranges, so a resume with
    another E is another recipe and its scenes redraw with their own stiffness."""
    from diffgns.io.families_data import families_recipe

    stiff = families_recipe(FAMS, 3, 4, young_modulus=2.0e7)
    assert stiff["ranges"]["young_modulus"] == 2.0e7
    assert families_recipe(FAMS, 3, 4, flip=0.99)["ranges"]["flip"] == 0.99
    assert families_recipe(FAMS, 3, 4)["ranges"]["young_modulus"] == 2.0e6
    assert stiff != families_recipe(FAMS, 3, 4)
    path = tmp_path / "r.h5"
    with h5py.File(path, "w") as f:
        f.attrs["recipe"] = json.dumps(stiff)
    scene = random_sample("columns", 9, **read_ranges(path))[0]
    assert {b.material.E for b in scene.bodies} == {2.0e7}


def test_cli_refuses_column_pairs_in_a_box_too_long_for_them_to_meet(tmp_path, capsys):
    out = tmp_path / "x.h5"
    assert main(["dataset", "--kind", "granular", "--families", "column_pair", "--boxes",
                 "1.4x0.35", "--n", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--families, --boxes" in err and "near enough to meet" in err
    assert not out.exists()


@pytest.mark.slow  # two MPM compilations
def test_held_out_compositions_in_a_longer_box_keep_their_box_in_the_recipe(tmp_path):
    """The held-out sets of issue 21: a composition never trained on, in a box 1.75 x the
    longest training box; the recipe stores the box, so a resume with another box is refused
    and the scenes can be redrawn from (family, scene seed, recipe ranges)."""
    out = tmp_path / "long.h5"
    assert main(["dataset", "--kind", "granular", "--families", "column_hit", "squares",
                 "--boxes", "1.4x0.35", "--n", "2", "--frames", "3", "--seed", "5",
                 "--out", str(out)]) == 0
    trajs = load_dataset(out)
    assert [tuple(map(tuple, t.bounds)) for t in trajs] == [((0.0, 1.4), (0.0, 0.35))] * 2
    assert read_families(out) == {"00000": "column_hit", "00001": "squares"}
    with h5py.File(out, "r") as f:
        recipe = json.loads(f.attrs["recipe"])
    assert recipe["ranges"]["boxes"] == [[1.4, 0.35]]
    with h5py.File(out, "r") as f:
        seeds = [int(f[k].attrs["scene_seed"]) for k in ("00000", "00001")]
    redrawn = [random_sample(fam, s, **read_ranges(out))[0] for fam, s in
               zip(["column_hit", "squares"], seeds)]
    assert [sc.n_particles for sc in redrawn] == [t.n_particles for t in trajs]
    assert random_sample("squares", seeds[1])[0].domain != redrawn[1].domain
    with pytest.raises(InputError, match="different recipe"):
        generate_families(out, ["column_hit", "squares"], 2, 3, seed=5, progress=False)


def test_a_model_trained_on_granular_data_records_its_mpm_and_its_sand(tmp_path):
    """train_loop reads dx, particles per cell and the sand's E from the datasets' recipes
    (the general model's support check needs them: without dx it accepted 8-cell scenes,
    without E a model trained on 20 MPa sand would take 2 MPa scenes for its own); datasets
    of two resolutions or two sands are refused, and a file made before the recipe recorded
    E has the default sand."""
    from diffgns.graph.support import ModelSource, UnsupportedSceneError, check_scene
    from diffgns.graph.train_loop import _granular_source

    def fake(name, **ranges):
        with h5py.File(tmp_path / name, "w") as f:
            f.attrs["recipe"] = json.dumps({"ranges": ranges})
        return tmp_path / name

    res = dict(dx=0.1 / 16, particles_per_cell=4)
    a = fake("a.h5", **res, boxes=[[0.8, 0.35]])
    b = fake("b.h5", **res, young_modulus=2.0e6)
    src = _granular_source([a, b])
    assert {k: src[k] for k in res} == res
    assert src["material"] == dict(E=2.0e6, nu=0.3, rho=1800.0, cohesion=0.0)
    assert src["flip"] == 0.0  # files made before the recipe recorded the transfer
    with pytest.raises(InputError, match="different MPMs"):
        _granular_source([a, fake("c.h5", dx=0.1 / 8, particles_per_cell=4)])
    stiff = fake("s.h5", **res, young_modulus=2.0e7)
    with pytest.raises(InputError, match="one sand"):
        _granular_source([a, stiff])
    flip = fake("f.h5", **res, flip=0.99)
    with pytest.raises(InputError, match="transfer"):
        _granular_source([a, flip])
    info = dict(source=dict(_granular_source([stiff]), kind="granular", dt=2.5e-3,
                            bounds=[[0, 0.8], [0, 0.5]], boxes=[[[0, 0.8], [0, 0.35]]]),
                gns=dict(bounds=[[0, 0.8], [0, 0.5]]), factor=16)
    assert ModelSource.from_info(info).material["E"] == 2.0e7
    soft_scene, _ = random_sample("columns", 2, boxes=((0.8, 0.35),))
    stiff_scene, _ = random_sample("columns", 2, boxes=((0.8, 0.35),), young_modulus=2.0e7)
    check_scene(stiff_scene, info)
    with pytest.raises(UnsupportedSceneError, match=r"E = 2e\+06 \(trained on 2e\+07\)"):
        check_scene(soft_scene, info)
    # a model of the MPM with a FLIP update refuses an APIC scene, and the other way round
    info_flip = dict(info, source=dict(info["source"], **_granular_source([flip])))
    check_scene(soft_scene.replace(flip=0.99), info_flip)
    with pytest.raises(UnsupportedSceneError, match="flip = 0, but the model emulates the "
                       "MPM with flip = 0.99"):
        check_scene(soft_scene, info_flip)
    with pytest.raises(UnsupportedSceneError, match="flip = 0.99, but"):
        check_scene(soft_scene.replace(flip=0.99), dict(info, source=dict(
            info["source"], **_granular_source([a]))))
