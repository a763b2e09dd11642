"""Scenario files: the shipped ones are usable, bad ones fail with the file and field named."""

import numpy as np
import pytest

from common.sim import ScenarioError, Simulator, World, load_scenario, parse_scenario, scenario_path
from common.sim.scenario import SCENARIO_DIR

SHIPPED = sorted(SCENARIO_DIR.glob("*.toml"))


def test_the_required_scenarios_ship():
    names = {p.stem for p in SHIPPED}
    assert {"corridor", "corridor_poor_texture", "trolley", "deep", "obstacles_boxes", "obstacles_doorway",
            "obstacles_dead_end"} <= names


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_shipped_scenarios_load_with_free_start_and_target(path):
    scn = load_scenario(path)
    world = World(scn)
    assert world.min_clearance(*scn.start[:2]) > 0.05
    if scn.target is not None:
        assert world.min_clearance(*scn.target) > 0.05
    if scn.name.startswith("obstacles_"):
        assert scn.target is not None and scn.path is None
    else:
        assert scn.path is not None


def test_corridor_dimensions():
    world = World(load_scenario(scenario_path("corridor")))
    segs = world.obstacle_segments(0.1, 2.0)
    ys = segs[..., 1]
    long_walls = segs[np.abs(ys[:, 0] - ys[:, 1]) < 1e-9]
    assert 20 <= np.ptp(long_walls[..., 0]) <= 25
    assert np.ptp(long_walls[..., 1]) == pytest.approx(2.0)


def _minimal(**extra):
    data = {"robot": {"start": [0.0, 0.0, 0.0]},
            "walls": [{"from": [2.0, -1.0], "to": [2.0, 1.0], "z": [0.0, 2.0]}]}
    data.update(extra)
    return data


@pytest.mark.parametrize("data, message", [
    (_minimal(walls=[{"from": [2.0, -1.0, 0.0], "to": [2.0, 1.0], "z": [0.0, 2.0]}]),
     r"walls\[0\]\.from: expected 2 numbers, got 3 values"),
    (_minimal(walls=[{"from": [2.0, -1.0], "to": [2.0, 1.0]}]), r"walls\[0\]\.z: missing"),
    (_minimal(walls=[{"from": [2.0, -1.0], "to": [2.0, 1.0], "z": [2.0, 0.0]}]), r"walls\[0\]\.z: needs z0 < z1"),
    (_minimal(walls=[{"from": [2.0, -1.0], "to": [2.0, 1.0], "z": [0.0, 2.0], "texure": "brick"}]),
     r"walls\[0\]: unknown key\(s\) texure"),
    (_minimal(walls=[{"from": [2.0, -1.0], "to": [2.0, 1.0], "z": [0.0, 2.0], "texture": "marble"}]),
     r"walls\[0\]\.texture: 'marble' is neither"),
    (_minimal(textures={"t": {"kind": "brick", "resolution": 100}}), r"textures\.t: .*power of two"),
    (_minimal(camera={"baseline": -0.1}), r"camera\.baseline: must be a number|camera\.baseline: must be positive"),
    (_minimal(camera={"width": "640"}), r"camera\.width: expected an integer"),
    (_minimal(odometry={"radius_error_left": 0.9}), r"odometry\.radius_error_left"),
    (_minimal(path={"mode": "teleport"}), r"path\.mode: expected one of"),
    (_minimal(path={"mode": "waypoints", "waypoints": [[1.0, 2.0, 3.0]]}), r"path\.waypoints\[0\]"),
    (_minimal(boxes=[{"center": [1.0, 1.0], "size": [1.0, 0.0, 1.0]}]), r"boxes\[0\]\.size: all three"),
    (_minimal(panels=[{"origin": [0, 0, 0], "u": [1.0, 0, 0], "v": [1.0, 1.0, 0], "texture": "light"}]),
     r"panels\[0\]: u and v must be perpendicular"),
    (_minimal(robto={}), r"top level: unknown key\(s\) robto"),
])
def test_bad_scenarios_name_the_field(data, message):
    with pytest.raises(ScenarioError, match=r"bad\.toml: " + message):
        parse_scenario(data, "bad.toml")


def test_file_errors_name_the_file(tmp_path):
    with pytest.raises(ScenarioError, match="missing.toml: cannot read"):
        load_scenario(tmp_path / "missing.toml")
    bad = tmp_path / "broken.toml"
    bad.write_text("[robot\nstart = 1")
    with pytest.raises(ScenarioError, match="broken.toml: not valid TOML"):
        load_scenario(bad)
    with pytest.raises(ScenarioError, match="no scenario 'nope'.*corridor"):
        scenario_path("nope")


def test_scenario_error_is_a_value_error():
    assert issubclass(ScenarioError, ValueError)


def test_obstacle_segments_respect_the_height_band():
    data = _minimal(boxes=[{"center": [0.0, 2.0], "size": [0.5, 0.5, 0.4]},
                           {"center": [0.0, -2.0], "size": [0.5, 0.5, 0.4], "z0": 1.5}])
    world = World(parse_scenario(data, "band"))
    assert world.obstacle_segments(0.05, 0.3).shape == (1 + 4, 2, 2)       # wall + low box
    assert world.obstacle_segments(1.0, 1.2).shape == (1, 2, 2)            # wall only
    assert world.obstacle_segments(1.6, 1.7).shape == (1 + 4, 2, 2)        # wall + raised box
    assert world.obstacle_segments(2.5, 3.0).shape == (0, 2, 2)
    with pytest.raises(ValueError, match="z_min"):
        world.obstacle_segments(1.0, 0.5)


def test_clearance_is_the_distance_to_the_nearest_obstacle_and_negative_inside_boxes():
    data = _minimal(boxes=[{"center": [0.0, 2.0], "size": [1.0, 1.0, 0.5]}])
    world = World(parse_scenario(data, "clear"))
    d = world.clearance(np.array([[0.0, 0.0], [1.5, 0.0], [0.0, 2.0], [0.0, 1.2]]))
    np.testing.assert_allclose(d, [1.5, 0.5, -0.5, 0.3], atol=1e-12)
    assert world.min_clearance(1.5, 0.0, robot_radius=0.2) == pytest.approx(0.3)
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        world.clearance(np.zeros((3, 3)))


def test_named_bare_and_inline_textures():
    data = _minimal(textures={"red": {"kind": "paint", "color": [200, 0, 0]}},
                    posters=[{"from": [1.9, -0.5], "to": [1.9, 0.5], "z": [1, 2]},
                             {"from": [1.9, 0.5], "to": [1.9, 0.9], "z": [1, 2]}],
                    boxes=[{"center": [1.0, 1.0], "size": [0.2, 0.2, 0.2], "texture": "red"},
                           {"center": [1.0, -1.0], "size": [0.2, 0.2, 0.2], "texture": {"kind": "wood", "seed": 4}}])
    scn = parse_scenario(data, "tex")
    posters = [s for s in scn.surfaces if s.name.startswith("posters")]
    assert posters[0].texture != posters[1].texture  # every bare poster gets its own seed
    assert scn.boxes[0].texture.color == (200, 0, 0)
    assert scn.boxes[1].texture.seed == 4


def _render(name, t=1.0, w=160, h=120, noise=True):
    scn = load_scenario(scenario_path(name))
    if not noise:
        scn.camera.read_noise = scn.camera.shot_noise = 0.0
    sim = Simulator(scn, seed=0, width=w, height=h)
    sim.advance(t)
    return sim.render()


def test_deep_scene_spans_near_and_far_depths_and_sky():
    d = _render("deep").depth
    finite = d[np.isfinite(d)]
    assert np.isinf(d).mean() > 0.1                      # sky
    assert finite.min() < 3.0 and np.percentile(finite, 99) > 25.0


def test_poor_texture_corridor_has_much_less_image_texture_than_the_default():
    def textured_fraction(img):  # pixels with a horizontal step of more than 2 grey levels
        g = img.astype(float).mean(axis=2)
        return np.mean(np.abs(np.diff(g, axis=1)) > 2)
    rich = _render("corridor", t=3.0, w=320, h=240, noise=False).left
    poor = _render("corridor_poor_texture", t=3.0, w=320, h=240, noise=False).left
    assert textured_fraction(rich) > 0.1
    assert textured_fraction(poor) < 0.3 * textured_fraction(rich)
