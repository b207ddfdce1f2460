"""Generate the built-in plant: one thin sapling on a dark backdrop, seen from afar by a few cameras.

The orchard's opposite, for seeing how the pipeline does on a capture it was not tuned for: a small
object (`plant_height`, 300 mm by default) in millimetres, not metres; a stem and twigs only a few
pixels wide; 18 views instead of 80, from `distance` (2.4 m, eight plant heights) through a narrow
lens (`fov_deg` 10) so the plant still fills most of the frame; no ground and a near-black,
softly mottled backdrop with sensor noise, so there is little texture for matching.

World frame: millimetres, z up, stem base at the origin. Cameras stand on rings at the elevations
`elevations_deg` (seen from the plant's centre) and look at the centre of the plant's box.

Output: the capture layout of `srfpipe.scenes.capture` with classes background 0, stem 1 (stem,
twigs, leaf and berry stalks), leaf 2, berry 3; meshes stem/leaf/berry.ply, berries.json
([{"centre", "radius"}]) and scene.json with `units: "millimetre"` and the plant's tight box as
`object_bounds_world`. There is deliberately no `bounds_world`: the poses stage takes that key as
the scene bounds, and this scene's bounds must come from the data (for benchmarks to compare).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from srfpipe.config import ConfigError, stage_options, validate_scene
from srfpipe.scenes.capture import add_generator_arguments, check_views, intrinsics_for, ring_poses, write_capture
from srfpipe.scenes.raycast import (
    Lighting, Part, Renderer, mix_colours, fbm, leaf_albedo, light_direction, spots, value_noise,
)
from srfpipe.scenes.sapling import TRIANGLES_PER_LEAF, build_sapling
from srfpipe.scenes.tree import UNIT_SPHERE

log = logging.getLogger(__name__)

CLASSES = ["background", "stem", "leaf", "berry"]
STEM, LEAF, BERRY = 1, 2, 3
METRES_PER_MM = 1e-3  # the orchard's leaf texture is defined per metre
LIGHT_ELEVATION_DEG = (35.0, 60.0)  # studio key light, range over seeds
AMBIENT = 0.3
KEY_LIGHT = 0.95
SHADOW_BIAS = 7e-4  # of plant_height: off the surface, yet well inside the thinnest stalk
BACKDROP_DARK = 0.0006  # linear RGB levels of the backdrop, about 9 and 18 of 255 once encoded
BACKDROP_LIGHT = 0.003
BACKDROP_MOTTLE = 8.0  # noise cells per radian of view direction: a soft grade across a narrow view


# ----------------------------------------------------------------------------- materials


def stem_albedo(x: np.ndarray, height: float, seed: int, footprint=None) -> np.ndarray:
    """Green young wood, browner towards the base, with fine lengthwise streaks (frequencies per mm)."""
    woody = np.clip(1.0 - x[:, 2] / (0.6 * height), 0.0, 1.0)
    base = mix_colours([0.16, 0.30, 0.07], [0.30, 0.20, 0.11], woody)
    streaks = fbm(x * np.array([1.0, 1.0, 0.2], np.float32), 0.6, seed + 41, octaves=2, footprint=footprint)
    return base * (0.6 + 0.8 * streaks)[:, None]


def berry_albedo(x: np.ndarray, hue: np.ndarray, seed: int, footprint=None) -> np.ndarray:
    """Scarlet to orange per berry (hue in [0, 1]) with pale lenticel dots (frequencies per mm)."""
    albedo = mix_colours([0.62, 0.03, 0.03], [0.80, 0.28, 0.02], hue)
    albedo = albedo * (0.85 + 0.3 * fbm(x, 0.4, seed + 51, octaves=2, footprint=footprint))[:, None]
    return mix_colours(albedo, [0.85, 0.70, 0.45], spots(x, 1.2, seed + 52, 0.06, footprint))


def backdrop(seed: int):
    """A near-black backdrop far away: brightness depends on the ray direction only, like a sky."""

    def colour(directions: np.ndarray) -> np.ndarray:
        mottle = value_noise(directions * BACKDROP_MOTTLE, 1.0, seed + 61)
        level = BACKDROP_DARK + (BACKDROP_LIGHT - BACKDROP_DARK) * mottle
        return level[:, None] * np.array([1.0, 0.97, 0.92], np.float32)  # a faintly warm black

    return colour


def plant_parts(sapling, seed: int) -> list[Part]:
    """The plant's surfaces with their materials, in class order."""
    def leaf(x, pid, footprint):
        return leaf_albedo(x * METRES_PER_MM, sapling.leaf_tint[pid // TRIANGLES_PER_LEAF], seed,
                           footprint * METRES_PER_MM)

    def berry(x, pid, footprint):
        return berry_albedo(x, sapling.berry_hue[pid // len(UNIT_SPHERE.triangles)], seed, footprint)

    return [
        Part("stem", sapling.stem, STEM, lambda x, pid, fp: stem_albedo(x, sapling.height, seed, fp)),
        Part("leaf", sapling.leaf, LEAF, leaf, translucency=0.15),
        Part("berry", sapling.berry, BERRY, berry, sapling.berry_centres, sapling.berry_radius),
    ]


# ----------------------------------------------------------------------------- cameras


def camera_poses(views: int, elevations_deg: list[float], distance: float, target: np.ndarray,
                 rng: np.random.Generator) -> np.ndarray:
    """(views, 4, 4) on rings at `distance` from `target`, one ring per elevation, views split evenly."""
    elevations = np.radians(np.asarray(elevations_deg, np.float64))
    heights = target[2] + distance * np.sin(elevations)
    # jitter in height proportional to the distance: the orchard's default is in metres
    return ring_poses(views, heights.tolist(), distance * np.cos(elevations), target, rng,
                      height_jitter=0.01 * distance)


# ----------------------------------------------------------------------------- entry points


def generate_plant(out_dir: str | Path, progress: bool = True, **options) -> Path:
    """Build the plant, render every view and write the capture folder atomically; returns its path.

    `options` are the scene schema's `plant` keys (seed, plant_height, n_twigs, leaves_per_twig,
    n_berries, views, width, height, fov_deg, distance, elevations_deg, sensor_noise); missing keys
    take the schema defaults, unknown or invalid ones raise ValueError.
    """
    params = validate_scene({"plant": dict(options)}, "generate_plant options")["plant"]
    out = Path(out_dir)
    started = time.perf_counter()
    seed = params["seed"]
    sapling = build_sapling(seed, params["plant_height"], params["n_twigs"], params["leaves_per_twig"],
                            params["n_berries"])
    if sapling.info["n_berries"] < params["n_berries"]:
        log.warning("placed %d of %d berries (no more free space near the twig tips)",
                    sapling.info["n_berries"], params["n_berries"])
    rng = np.random.default_rng([seed, 1])  # views and light: independent of the plant stream
    light = light_direction(rng, LIGHT_ELEVATION_DEG)
    box = sapling.bounds
    target = box.mean(0)
    try:
        poses = camera_poses(params["views"], params["elevations_deg"], params["distance"], target, rng)
    except ValueError as exc:  # look_at: a camera straight below or above the plant's centre
        raise ConfigError(f"plant (distance {params['distance']:g}, elevations_deg {params['elevations_deg']}): "
                          f"a camera cannot be aimed at the plant ({exc})") from None
    width, height = params["width"], params["height"]
    check_views("plant", poses, intrinsics_for(width, height, params["fov_deg"]), width, height,
                ring_keys="distance, elevations_deg")
    lighting = Lighting(light, backdrop(seed), ambient=AMBIENT, sun_strength=KEY_LIGHT,
                        shadow_bias=SHADOW_BIAS * params["plant_height"])
    scene = {
        "world_frame": "millimetres, z up, stem base at the origin, no ground",
        "units": "millimetre",
        "object_bounds_world": box.tolist(),
        "parameters": params,
        "look_at_target": target.tolist(),
        "light_direction": light.tolist(),
        "plant": sapling.info,
    }
    berries = [{"centre": c.tolist(), "radius": sapling.berry_radius} for c in sapling.berry_centres]
    written = write_capture(
        out, Renderer(plant_parts(sapling, seed), lighting), poses,
        intrinsics_for(width, height, params["fov_deg"]), width, height, CLASSES,
        {"stem": sapling.stem, "leaf": sapling.leaf, "berry": sapling.berry}, scene,
        files={"berries.json": berries}, progress=progress, desc="plant views",
        sensor_noise=params["sensor_noise"], noise_seed=seed,
        subject_keys="plant.plant_height, distance, fov_deg",
    )
    log.info(
        "plant seed %d: %d twigs, %d leaves, %d berries, box %s mm; %d views of %dx%d in %.1f s -> %s",
        seed, sapling.info["n_twigs"], sapling.info["n_leaves"], sapling.info["n_berries"],
        np.round(box[1] - box[0]).tolist(), len(poses), width, height, time.perf_counter() - started, out,
    )
    log.info("pixels per class over all views: %s", written["class_pixel_counts"])
    return out


def add_arguments(parser) -> None:
    add_generator_arguments(parser, "plant")


def run(args) -> int:
    generate_plant(args.out, progress=not args.no_progress, **stage_options(args, "plant"))
    return 0
