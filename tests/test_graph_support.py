"""Which scenes a trained GNS supports: every refusal names its mismatch; supported scenes
give the model's observation operator (particles per node, frame stride)."""
import json

import pytest

from diffgns.graph.support import ModelSource, UnsupportedSceneError, check_scene, node_factor
from diffgns.models import model_path
from diffgns.scene import Body, BoxObstacle, Elastic, Rectangle, Sand, Scene, Wall, Walls
from diffgns.scene.builders import column_collapse


def _info(name="gns_columns"):
    return json.loads((model_path(name) / "config.json").read_text())


def _scene(**kw):
    """A sand square sliding into a box in the 0.8 x 0.35 m box of gns_columns, 8 cells per
    0.1 m, 4 particles per cell, 2.5 ms frames: a supported non-column scene."""
    material = kw.pop("material", Sand(friction_angle=30.0))
    ppc = kw.pop("particles_per_cell", 4)
    body = Body(Rectangle(0.05, 0.0, 0.15, 0.1), material, velocity=(1.0, 0.0),
                particles_per_cell=ppc, name="mass")
    args = dict(domain=((0.0, 0.8), (0.0, 0.35)), dx=0.0125, bodies=(body,),
                walls=Walls(bottom=Wall("friction", 0.5)),
                obstacles=(BoxObstacle(0.25, 0.0, 0.35, 0.05),), frame_dt=2.5e-3)
    args.update(kw)
    return Scene(**args)


def test_model_source_reads_the_model_folder():
    src = ModelSource.from_info(_info())
    assert src.bounds == ((0.0, 0.8), (0.0, 0.35000000000000003))
    assert src.dx == pytest.approx(0.0125) and src.particles_per_cell == 4
    assert (src.factor, src.frame_stride, src.frame_dt) == (4, 2, 2.5e-3)
    assert src.material == {"E": 2e6, "nu": 0.3, "rho": 1800.0, "cohesion": 0.0}
    assert ModelSource.from_info(_info("gns_cg16")).dx == pytest.approx(0.00625)


def test_a_supported_non_column_scene_runs_with_warnings():
    sup = check_scene(_scene(), _info())
    assert (sup.factor, sup.frame_stride) == (4, 2)
    text = " ".join(sup.warnings)
    assert "obstacle" in text and "moving" in text
    # the training column itself: no warning
    col = column_collapse(width=0.1, aspect_ratio=1.0, cells_across=8, domain_length=0.8,
                          domain_height=0.35)
    assert check_scene(col, _info()).warnings == ()


def test_column_model_warns_off_the_left_wall_and_moving_bodies_only_when_untrained():
    """A column-only model (trained against the left wall, at rest) warns for a column against
    the right wall; a model whose training families had moving bodies does not warn that
    bodies move, one with mirror augmentation not about the wall."""
    column = Body(Rectangle(0.7, 0.0, 0.8, 0.1), Sand(friction_angle=30.0),
                  particles_per_cell=4, name="column")
    right = _scene(bodies=(column,), obstacles=())
    (w,) = check_scene(right, _info()).warnings
    assert "does not rest against the left wall (x = 0 m)" in w
    assert check_scene(right, dict(_info(), mirror=0.5)).warnings == ()
    general = dict(_info(), families=["columns", "squares"])
    assert not any("moving" in w for w in check_scene(_scene(), general).warnings)
    assert any("moving" in w for w in check_scene(_scene(), dict(_info(), families=[
        "columns"])).warnings)


@pytest.mark.parametrize("change,expected", [
    (dict(domain=((0.0, 1.0), (0.0, 0.35))), r"box \[0, 1\] x \[0, 0.35\] m is not the "
     r"training box \[0, 0.8\] x \[0, 0.35\] m"),
    (dict(material=Elastic()), "body mass is elastic, but the model was trained on sand"),
    (dict(material=Sand(friction_angle=30.0, E=1e6)), r"E = 1e\+06 \(trained on 2e\+06\)"),
    (dict(material=Sand(friction_angle=30.0, cohesion=100.0)), r"cohesion = 100 \(trained on "
     r"0\)"),
    (dict(dx=0.00625), "cell size dx = 0.00625 m is not the 0.0125 m the model emulates"),
    (dict(particles_per_cell=9), r"particles per cell \[9\] are not the 4"),
    (dict(frame_dt=5e-3), r"frame_dt = 0.005 s gives GNS frames of 0.01 s .* the model steps "
     "0.005 s"),
])
def test_each_refusal_names_the_mismatch(change, expected):
    with pytest.raises(UnsupportedSceneError, match=expected) as e:
        check_scene(_scene(**change), _info(), model="gns_columns")
    assert str(e.value).startswith("gns_columns cannot simulate this scene")


def test_all_mismatches_are_named_at_once():
    with pytest.raises(UnsupportedSceneError) as e:
        check_scene(_scene(dx=0.025, frame_dt=1e-3, material=Elastic()), _info())
    msg = str(e.value)
    assert "elastic" in msg and "dx = 0.025" in msg and "frame_dt = 0.001" in msg


def test_node_spacing_mode_keeps_the_trained_node_spacing():
    """A hybrid on a finer MPM groups more particles per node (same node spacing)."""
    assert check_scene(_scene(dx=0.00625), _info(), resolution="node-spacing").factor == 16
    assert check_scene(_scene(particles_per_cell=16), _info(), "node-spacing").factor == 16
    assert check_scene(_scene(particles_per_cell=9), _info(), "node-spacing").factor == 9
    with pytest.raises(UnsupportedSceneError, match="6.25 particles per node, not a whole"):
        check_scene(_scene(dx=0.01), _info(), "node-spacing")
    assert node_factor(4, 0.00625, 0.003125) == 16
    with pytest.raises(ValueError, match="'exact' or 'node-spacing'"):
        check_scene(_scene(), _info(), resolution="any")


def test_a_friction_angle_outside_the_training_data_is_a_warning_with_its_range():
    """gns_columns was trained on 20-45 deg: a body at 15 or 50 deg runs, with a warning that
    names the body, the angle and the range; the edges of the range give none; a model folder
    that does not record its range (made before it was) gives none."""
    from diffgns.graph.support import friction_warnings

    info = _info()
    assert ModelSource.from_info(info).friction_angle == (20.0, 45.0)
    for phi in (20.0, 45.0, 30.0):
        assert check_scene(_scene(material=Sand(friction_angle=phi)), info,
                           ).warnings == check_scene(_scene(), info).warnings
    for phi in (15.0, 50.0):
        w = [w for w in check_scene(_scene(material=Sand(friction_angle=phi)), info).warnings
             if "friction" in w]
        assert w == [f"body friction_angle[mass] = {phi:.2f} deg is outside the 20.0-45.0 deg "
                     "of the model's training data: the network's material input "
                     "tan(friction_angle) is extrapolated there, and the result is not one "
                     "the model was trained to give"]
    old = dict(info, source={k: v for k, v in info["source"].items() if k != "friction_angle"})
    assert ModelSource.from_info(old).friction_angle is None
    assert friction_warnings({"friction_angle": 60.0}, old) == []
    # inversion parameters: only friction angles are checked, by name or body
    got = friction_warnings({"friction_angle": 19.99, "friction_angle[column]": 45.00005,
                             "E": 1e9, "friction_angle[1]": 45.01}, info, "the")
    assert [g.split(" deg")[0] for g in got] == ["the friction_angle = 19.99",
                                                 "the friction_angle[1] = 45.01"]


def test_training_records_the_friction_range_of_its_data():
    """``friction_range`` reads tan(phi) per particle; data without a material (zeros) have
    none; the shipped general model's range is that of its training data's recipe."""
    import numpy as np

    from diffgns.graph.train_loop import friction_range

    class T:
        def __init__(self, phis):
            self.material = np.tan(np.radians(np.asarray(phis, np.float32)))

    assert friction_range([T([30.0] * 4), T([17.5, 17.5]), T([42.0])]) == pytest.approx(
        [17.5, 42.0], abs=1e-5)
    assert friction_range([T([0.0, 0.0])]) is None and friction_range([]) is None
    from diffgns.scene.materials import friction_angle_of_feature, friction_feature

    assert friction_angle_of_feature(friction_feature(33.0)) == pytest.approx(33.0, abs=1e-5)
    lo, hi = ModelSource.from_info(_info("gns_general")).friction_angle
    assert 15.0 <= lo < 15.5 and 44.5 < hi <= 45.0  # the recipe draws 15-45 deg
