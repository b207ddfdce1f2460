"""The simulator package and runtime: fruit instances, contact, units, the Gymnasium env, policies.

Most tests run on an analytic tree (capsule branches, sphere apples: srfpipe.occupancy.AnalyticField)
whose answers are known in closed form; one builds the tiny test orchard's package through Snakemake
and runs a short rollout on it.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest

import srfpipe.sim  # noqa: E402,F401  (first: it picks MuJoCo's headless OpenGL back end, EGL)

pytest.importorskip("mujoco")
gym = pytest.importorskip("gymnasium")

from srfpipe.config import section_defaults  # noqa: E402
from srfpipe.occupancy import AnalyticField, distill  # noqa: E402
from srfpipe.sim.package import find_instances, match_ground_truth, package  # noqa: E402
from srfpipe.sim.runtime import DistanceFields, Simulator, capsule_contact  # noqa: E402

CLASSES = ["apple", "branch", "leaf"]
BOUNDS = np.array([[-0.8, -0.8, 0.0], [0.8, 0.8, 1.6]])
APPLES = [((0.45, 0.05, 1.02), 0.05), ((-0.35, 0.38, 1.12), 0.05), ((0.12, -0.42, 0.86), 0.05)]
BRANCHES = [((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.05), ((0.0, 0.0, 0.8), (0.6, 0.05, 1.2), 0.025),
            ((0.0, 0.0, 0.85), (-0.45, 0.5, 1.3), 0.025), ((0.0, 0.0, 0.7), (0.15, -0.55, 1.05), 0.025)]


def analytic_tree(scale: float = 1.0, unit: str | None = "metre") -> AnalyticField:
    """Branches (avoid) and apples hanging just below them (reach), `scale` world units per metre."""
    tree = AnalyticField(list(CLASSES), BOUNDS * scale, sigma=1000.0 / scale, unit=unit)
    for start, end, radius in BRANCHES:
        tree.add_capsule(np.multiply(start, scale), np.multiply(end, scale), radius * scale, "branch")
    for centre, radius in APPLES:
        tree.add_sphere(np.multiply(centre, scale), radius * scale, "apple")
    return tree


def build_package(tmp_path, tree: AnalyticField, voxel: float, options: dict | None = None, name="sim"):
    cache = distill(tree, tmp_path / f"{name}_occupancy.zarr",
                    {"voxel_size": voxel, "avoid": ["branch"], "reach": ["apple"], "unit": tree.unit}, progress=False)
    return package(cache, None, tmp_path / name, {**section_defaults("sim"), **(options or {})}, field=tree)


@pytest.fixture(scope="module")
def tree_package(tmp_path_factory):
    return build_package(tmp_path_factory.mktemp("tree"), analytic_tree(), voxel=0.025)


# ------------------------------------------------------------------------------------------ packaging


def test_instances_are_the_apples_with_centroid_radius_and_voxels(tree_package):
    manifest = json.loads((tree_package / "scene.json").read_text())
    targets = json.loads((tree_package / "targets.json").read_text())
    assert manifest["roles"] == {"avoid": ["branch"], "reach": ["apple"]}
    assert len(targets) == len(APPLES)
    truth = np.array([c for c, _ in APPLES])
    for t in targets:
        error = np.linalg.norm(truth - t["centroid"], axis=1).min()
        assert error < 0.25 * 0.05, f"centroid off by {error:.4f} m"
        assert 0.035 < t["radius"] < 0.065 and t["voxels"] > 20
    # the package is what the manifest says: files with hashes, an MJCF MuJoCo loads, meshes per class
    import mujoco

    model = mujoco.MjModel.from_xml_path(str(tree_package / "scene.xml"))
    assert model.nu == 5 and mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "target_0") >= 0
    for name in ("apple", "branch", "occupied"):
        assert f"meshes/{name}.ply" in manifest["files"] and (tree_package / f"meshes/{name}.ply").exists()
    assert manifest["srfpipe"]["stage"] == "package" and "mujoco" in manifest["versions"]


def test_touching_fruit_are_split_and_matched_to_ground_truth():
    grid = np.zeros((20, 20, 40), dtype=bool)
    z, y, x = np.mgrid[:20, :20, :40]
    for cx in (13.0, 24.0):  # two balls of radius 6 voxels whose surfaces overlap
        grid |= (x - cx) ** 2 + (y - 10) ** 2 + (z - 10) ** 2 <= 36
    found = find_instances(grid, origin=(0, 0, 0), voxel_size=1.0)
    assert len(found) == 2
    truth = [{"centre": [13.5, 10.5, 10.5], "radius": 6.0}, {"centre": [24.5, 10.5, 10.5], "radius": 6.0},
             {"centre": [80.0, 0.0, 0.0], "radius": 6.0}]
    result = match_ground_truth(found, truth, match_radii=2.0)
    assert result["count"] == 2 and result["count_gt"] == 3 and result["matched"] == 2
    assert result["centroid_err_mean"] < 1.0


def test_scene_in_millimetres_is_scaled_to_metres(tmp_path):
    path = build_package(tmp_path, analytic_tree(scale=1000.0, unit="millimetre"), voxel=25.0)
    manifest = json.loads((path / "scene.json").read_text())
    assert manifest["units"]["metres_per_unit"] == pytest.approx(1e-3)
    assert manifest["units"]["unit"] == "millimetre"
    assert np.allclose(manifest["bounds_sim"], np.asarray(manifest["bounds_world"]) * 1e-3)
    targets = json.loads((path / "targets.json").read_text())
    assert np.allclose(sorted(t["radius_sim"] for t in targets), 0.05, atol=0.015)
    assert 0.5 < manifest["arm"]["reach"] < 1.5, "the arm is sized in metres, not in millimetres"


def test_scene_without_a_reach_class_packages_geometry_and_contact_only(tmp_path):
    tree = analytic_tree()
    cache = distill(tree, tmp_path / "occ.zarr", {"voxel_size": 0.05, "avoid": ["branch"], "reach": []}, progress=False)
    path = package(cache, None, tmp_path / "sim", section_defaults("sim"))
    manifest = json.loads((path / "scene.json").read_text())
    assert manifest["task"] is None and "geometry and contact only" in manifest["note"]
    assert json.loads((path / "targets.json").read_text()) == []
    sim = Simulator(path)
    assert sim.contact().clearance.shape == (4,)
    with pytest.raises(ValueError, match="no targets"):
        gym.make("srfpipe/AppleReach-v0", package=path)


# ------------------------------------------------------------------------------------------ contact


def test_link_inside_a_branch_is_in_contact_and_one_in_free_space_is_not(tree_package):
    sim = Simulator(tree_package)
    trunk_top = np.array([0.0, 0.0, 0.6])
    radius = np.array([0.02])
    inside = capsule_contact(sim.fields, trunk_top[None] - [[0, 0, 0.1]], trunk_top[None], radius, np.array([9]))
    assert inside.in_contact and inside.penetration > 0.05  # trunk radius 0.05 + link radius 0.02 - voxel error
    free = capsule_contact(sim.fields, np.array([[0.2, -0.1, 0.3]]), np.array([[0.2, 0.1, 0.3]]), radius, np.array([9]))
    assert not free.in_contact and free.penetration == 0.0
    # the nearest point of the link is (0.2, 0, 0.3), 0.2 m from the trunk's axis
    assert free.clearance[0] == pytest.approx(0.2 - 0.05 - 0.02, abs=0.015)
    # the gradient points away from the trunk (horizontally out, +x)
    assert free.gradient[0] > 0.9 and abs(free.gradient[2]) < 0.2

    # through MuJoCo: move the lift so a link passes through the trunk
    sim.reset()
    base_link = sim.link_segments()[0][1]
    assert not sim.contact().in_contact
    sim.data.mocap_pos[sim.mocap] += trunk_top - base_link
    import mujoco

    mujoco.mj_forward(sim.model, sim.data)
    assert sim.contact().in_contact


def test_distance_fields_are_finite_far_outside_the_grid(tree_package):
    sim = Simulator(tree_package)
    d, grad = sim.fields.query(np.array([[1e6, -1e6, 1e6], [0.0, 0.0, -50.0]]))
    assert np.all(np.isfinite(d)) and np.all(d > 1.0) and np.all(np.isfinite(grad))
    with pytest.raises(ValueError):
        sim.fields.query(np.array([[np.nan, 0.0, 0.0]]))
    assert isinstance(sim.fields, DistanceFields)


def test_whole_grid_distance_is_the_cache_s_and_mesh_colours_are_the_eval_renders(tree_package):
    """What package takes from other stages, through their public names: distill's whole-grid signed
    distance (the cache's own field, brick by brick there) and evaluate's class colours."""
    import zarr

    from srfpipe.evaluate import class_colours, class_rgba
    from srfpipe.occupancy import OccupancyCache
    from srfpipe.occupancy.distill import signed_distance_field

    cache = OccupancyCache.load(tree_package.parent / "sim_occupancy.zarr")
    trunc = float(cache.attrs["distance"]["truncation"])
    stored = zarr.open_group(str(cache.path), mode="r")["class_occupancy"]
    occupied = np.asarray(stored[cache.class_index("branch")], dtype=bool)
    field = signed_distance_field(occupied, cache.grid, trunc)
    assert field.dtype == np.float32 and field.shape == cache.grid.shape
    assert np.allclose(field, cache.distance_field("branch"), atol=1e-6)
    assert np.all(signed_distance_field(np.zeros_like(occupied), cache.grid, trunc) == np.float32(trunc))
    with pytest.raises(ValueError, match="no distance field"):
        cache.distance_field("leaf")
    rgba = class_rgba(CLASSES)
    assert list(rgba) == CLASSES and all(c[3] == 1.0 for c in rgba.values())
    assert np.allclose(np.array([c[:3] for c in rgba.values()]) * 255, class_colours(CLASSES)[1:])


@pytest.mark.parametrize("case", ["zero_focal", "tiny_focal", "zero_rotation", "scaled", "empty_image"])
def test_baked_render_refuses_a_view_that_is_no_camera(tree_package, case):
    """A zero focal length or a zero rotation gave NaN rays that crashed the process in the march
    kernel (a segmentation fault); a scaled rotation or a 0 x 0 image rendered without a word."""
    from srfpipe.sim.baked import BakedRenderer
    from tests.test_bad_inputs import BAD_VIEWS, _bad_view

    renderer = BakedRenderer(tree_package / "baked.zarr")
    pose, k, (width, height) = _bad_view(case)
    pose[:3, 3] = [0.0, -2.0, 1.0]
    with pytest.raises(ValueError, match=BAD_VIEWS[case]):
        renderer.render(pose, k, width, height)


# ------------------------------------------------------------------------------------------ env


def make_env(path, **kwargs):
    import srfpipe.sim  # noqa: F401  (registers the env)

    return gym.make("srfpipe/AppleReach-v0", package=path, wrist_size=32, **kwargs)


def test_check_env_passes(tree_package):
    from gymnasium.utils.env_checker import check_env

    env = make_env(tree_package)
    check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=0)
    assert obs["rgb"].shape == (32, 32, 3) and obs["semantic"].shape == (32, 32, 3)
    assert obs["rgb"].std() > 0, "the wrist camera should see the scene, not a flat colour"


def test_reward_rises_as_the_tip_approaches_the_target(tree_package):
    env = make_env(tree_package).unwrapped
    env.reset(seed=0, options={"target": 0})
    target = np.asarray(env.target_info["centroid_sim"])
    start = env.sim.tip()
    rewards = []
    for fraction in (0.0, 0.3, 0.6, 0.9):
        tip = start + fraction * (target - start)
        rewards.append(env.reward_for(env.target_distance(tip), False, False))
    assert all(a < b for a, b in zip(rewards, rewards[1:]))
    # and along a rollout of the scripted policy, which closes the distance
    from srfpipe.sim.policies import ScriptedPolicy

    policy = ScriptedPolicy(env)
    obs, info = env.reset(seed=0, options={"target": 0})
    first = None
    for _ in range(25):
        obs, reward, terminated, truncated, info = env.step(policy(obs, info))
        first = reward if first is None else first
        if terminated:
            break
    assert reward > first


def test_env_refuses_a_wrong_action_and_a_step_after_the_episode_ended(tree_package):
    """A step after success paid the success bonus again, every step, without a word; an action
    of the wrong shape said only that an array could not be reshaped, a NaN one named joint
    targets; a zero wrist size gave empty observations."""
    from srfpipe.sim.policies import ScriptedPolicy

    env = make_env(tree_package).unwrapped
    n = env.action_space.shape[0]
    obs, info = env.reset(seed=0, options={"target": 0})
    with pytest.raises(ValueError, match=re.escape(f"action must hold one value per joint, shape ({n},), got shape ({n + 1},)")):
        env.step(np.zeros(n + 1))
    with pytest.raises(ValueError, match="action must not be NaN"):
        env.step(np.full(n, np.nan))
    assert np.array_equal(env.sim.qpos, env.sim.home)  # the refused actions moved nothing
    policy = ScriptedPolicy(env)
    for _ in range(150):
        obs, reward, terminated, truncated, info = env.step(policy(obs, info))
        if terminated:
            break
    assert terminated
    with pytest.raises(RuntimeError, match=r"call reset\(\) first"):
        env.step(np.zeros(n))
    env.reset(seed=0)
    env.step(np.zeros(n))  # a new episode steps again
    for kwargs, problem in (({"wrist_size": 0}, "wrist_size must be at least 1"),
                            ({"max_delta": float("nan")}, "max_delta must be a positive number")):
        with pytest.raises(ValueError, match=problem):
            gym.make("srfpipe/AppleReach-v0", package=tree_package, **{"wrist_size": 32, **kwargs})


def test_same_seed_same_rollout(tree_package):
    from srfpipe.sim.policies import RandomPolicy

    def rollout(seed):
        env = make_env(tree_package)
        policy = RandomPolicy(env.action_space, seed=seed)
        obs, info = env.reset(seed=seed)
        trace = [info["target"]]
        for _ in range(6):
            obs, reward, terminated, truncated, info = env.step(policy(obs, info))
            trace += [reward, obs["rgb"].sum(), *obs["joints"]]
            if terminated or truncated:
                break
        return np.array(trace, dtype=np.float64)

    a, b = rollout(3), rollout(3)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, rollout(4))


# ------------------------------------------------------------------------------------------ workflow


@pytest.mark.workflow
def test_tiny_orchard_package_through_snakemake_and_a_short_rollout(workflow):
    from srfpipe.artifacts import read_provenance
    from tests.conftest import TINY_ORCHARD, snakemake_env

    scene = {**TINY_ORCHARD, "train": {"iterations": 30, "rays_per_batch": 256}, "occupancy": {"voxels_across": 48}}
    workflow.write_scene("tiny", scene)
    workflow.run("results/tiny/sim")
    path = workflow.root / "results/tiny/sim"
    manifest = json.loads((path / "scene.json").read_text())
    assert manifest["srfpipe"]["stage"] == "package"
    assert manifest["units"]["metres_per_unit"] == 1.0 and manifest["units"]["unit"] == "metre"
    assert manifest["classes"] == read_provenance(workflow.root / "results/tiny/occupancy.zarr")["classes"]
    assert manifest["ground_truth"]["apple"]["count_gt"] == TINY_ORCHARD["orchard"]["n_apples"]
    for name in manifest["files"]:
        assert (path / name).exists()
    assert (workflow.root / "logs/tiny/package.log").exists()

    gif = workflow.root / "rollout.gif"
    result = subprocess.run([sys.executable, "-m", "srfpipe.cli", "sim", "--package", str(path), "--episodes", "1",
                             "--max-steps", "4", "--wrist-size", "16", "--out", str(gif)],
                            capture_output=True, text=True, env=snakemake_env())
    assert result.returncode == 0, result.stderr[-3000:]
    from PIL import Image

    with Image.open(gif) as image:
        assert image.n_frames >= 1 and image.size[0] > image.size[1]  # wrist | semantic | third person


@pytest.mark.parametrize("flags, problem", [
    (["--episodes", "0"], "--episodes must be at least 1, got 0"),
    (["--episodes", "-2"], "--episodes must be at least 1, got -2"),
    (["--max-steps", "-1"], "--max-steps must be at least 1, got -1"),
    (["--seed", "-1"], "--seed must be at least 0, got -1"),
    (["--wrist-size", "0"], "--wrist-size must be at least 1, got 0"),
    (["--fps", "0"], "--fps must be a positive number, got 0.0"),
])
def test_sim_cli_refuses_flags_that_run_nothing_forever_or_fail_after_the_episodes(tree_package, tmp_path, capsys,
                                                                                   flags, problem):
    """0 episodes printed a NaN success rate (not JSON) and no GIF with exit 0; a negative --max-steps
    ran until contact (forever for a policy that avoids it); a negative seed and --fps 0 failed with
    a traceback after the episodes had run."""
    from srfpipe.cli import main

    gif = tmp_path / "rollout.gif"
    rc = main(["sim", "--package", str(tree_package), "--max-steps", "2", "--out", str(gif), *flags])
    assert rc == 1
    assert f"srfpipe sim: error: {problem}" in capsys.readouterr().err
    assert not gif.exists()
