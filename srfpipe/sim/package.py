"""Package a scene for the simulator: `srfpipe package` -> results/{scene}/sim/.

    srfpipe package --occupancy results/orchard/occupancy.zarr --srf results/orchard/srf.zarr \
        --images results/orchard/images.zarr --out results/orchard/sim

The folder (written atomically: built in a hidden sibling, renamed when complete):

    scene.json          the manifest: classes and roles (reach / avoid, from the cache), units and
                        the sim frame (MuJoCo works in metres: sim = world x metres_per_unit), bounds,
                        the field and cache it runs on (paths relative to this folder), fruit
                        instances, stations, files (sha256) and provenance (stage, config, versions)
    targets.json        instances of each reach class: centroid, radius, voxels (world and sim units),
                        the station the arm is placed at to reach it, and whether it is reachable;
                        with ground truth (apples.json / berries.json) the match to it
    meshes/{name}.ply   marching cubes of each class's occupancy (and `occupied`, all matter), world units
    meshes/{name}.stl   the same meshes in sim metres, the MJCF's visuals (MuJoCo reads no PLY)
    baked.zarr          the field sampled on the cache's grid (sigma, colour, class probabilities, sky) for
                        wrist renders at simulation rate (srfpipe.sim.baked); the network stays available
    scene.xml           MuJoCo MJCF: the meshes (visual only), a site per target, the arm with its
                        wrist camera on a lift at the first reachable target's station, an overview camera
    contact.zarr        only when the scene has no avoid class: the signed distance to all occupied
                        space (world units), so contact works on a scene without classes

A scene without a reach class (no classes, or none listed in occupancy.reach) packages geometry and
contact only (`task: null` in the manifest). Instances are the 26-connected components of the class
occupancy with at least `sim.min_instance_voxels` voxels; touching fruit are split by a watershed on
the distance to the component's surface (peaks at least `sim.split_min_radius_voxels` deep).

A target is *reachable* when a straight approach corridor exists: from some station (the arm's
shoulder on a line through the fruit, `sim.approach_reach` x reach away, from the sides and above) the
segment from the shoulder to the fruit's surface keeps more than the arm's thickest link radius from
every avoid class. The controller still has to bring the elbow and wrist through; the benchmark
measures whether it does.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from srfpipe.settings import OccupancySettings

log = logging.getLogger(__name__)

STAGE = "package"
MANIFEST_FORMAT = "srfpipe-sim-1"
UNIT_METRES = {"metre": 1.0, "meter": 1.0, "m": 1.0, "millimetre": 1e-3, "millimeter": 1e-3, "mm": 1e-3,
               "centimetre": 1e-2, "centimeter": 1e-2, "cm": 1e-2}


# ------------------------------------------------------------------------------------------------ units


def resolve_unit(options: dict, cache_unit: str | None, ground_truth: dict | None) -> dict:
    """Metres per world unit: `sim.metres_per_unit`, else the unit named by the config/cache, else the
    capture's ground truth (scene.json `units`), else unknown (taken as metres, and recorded so)."""
    if options.get("metres_per_unit") is not None:
        return {"unit": cache_unit, "metres_per_unit": float(options["metres_per_unit"]), "source": "config"}
    for unit, source in ((cache_unit, "occupancy"), ((ground_truth or {}).get("units"), "ground_truth")):
        if unit:
            key = str(unit).lower()
            if key not in UNIT_METRES:
                raise ValueError(f"unit {unit!r} ({source}) is not one of {sorted(UNIT_METRES)}; set sim.metres_per_unit")
            return {"unit": str(unit), "metres_per_unit": UNIT_METRES[key], "source": source}
    return {"unit": None, "metres_per_unit": 1.0, "source": "unknown: world units taken as metres"}


# ------------------------------------------------------------------------------------------------ instances


def find_instances(occupied: np.ndarray, origin, voxel_size: float, min_voxels: int = 4,
                   split_min_radius_voxels: float = 1.5) -> list[dict]:
    """Instances of one class's occupancy (z, y, x) grid: centroid (world xyz), radius, voxel count.

    26-connected components, each split by a watershed on its distance-to-surface map where it has
    several peaks at least `split_min_radius_voxels` deep and 2 such radii apart (touching fruit).
    radius is the equivalent sphere's, (3 n v^3 / 4 pi)^(1/3). Sorted by voxel count, largest first.
    """
    from scipy import ndimage

    occupied = np.asarray(occupied, dtype=bool)
    labels, n = ndimage.label(occupied, structure=np.ones((3, 3, 3), dtype=bool))
    if n == 0:
        return []
    labels = _split_touching(occupied, labels, n, split_min_radius_voxels)
    index = np.arange(1, labels.max() + 1)
    counts = ndimage.sum_labels(np.ones_like(labels, dtype=np.int64), labels, index).astype(np.int64)
    centres_zyx = np.asarray(ndimage.center_of_mass(occupied, labels, index), dtype=np.float64).reshape(-1, 3)
    out = []
    origin = np.asarray(origin, dtype=np.float64)
    for count, zyx in zip(counts, centres_zyx):
        if count < min_voxels:
            continue
        centre = origin + (zyx[::-1] + 0.5) * voxel_size
        radius = (3.0 * count / (4.0 * math.pi)) ** (1.0 / 3.0) * voxel_size
        out.append({"centroid": centre.tolist(), "radius": float(radius), "voxels": int(count)})
    out.sort(key=lambda d: -d["voxels"])
    return out


def _split_touching(occupied: np.ndarray, labels: np.ndarray, n: int, min_depth: float) -> np.ndarray:
    """Watershed each component from the peaks of its Euclidean distance map (skimage)."""
    from scipy import ndimage
    from skimage.feature import peak_local_max
    from skimage.segmentation import watershed

    depth = ndimage.distance_transform_edt(occupied)
    peaks = peak_local_max(depth, min_distance=max(1, int(round(2 * min_depth))), threshold_abs=min_depth,
                           labels=labels, exclude_border=False)
    if len(peaks) == 0:
        return labels
    markers = np.zeros(labels.shape, dtype=np.int64)
    markers[tuple(peaks.T)] = np.arange(1, len(peaks) + 1)
    # a component without a deep enough peak keeps its own marker
    has_peak = np.zeros(n + 1, dtype=bool)
    has_peak[labels[tuple(peaks.T)]] = True
    next_marker = len(peaks) + 1
    for component in np.flatnonzero(~has_peak[1:]) + 1:
        where = np.argwhere(labels == component)[0]
        markers[tuple(where)] = next_marker
        next_marker += 1
    return watershed(-depth, markers, mask=occupied, connectivity=3)


def match_ground_truth(instances: list[dict], truth: list[dict], match_radii: float) -> dict:
    """One-to-one matching of instance centroids to ground-truth centres (Hungarian, world units); a
    pair counts when its distance is below `match_radii` x the true radius. Returns the counts, the
    mean/median/max centroid error of the matches, and per instance the index of its match or None."""
    from scipy.optimize import linear_sum_assignment

    found = np.asarray([i["centroid"] for i in instances], dtype=np.float64).reshape(-1, 3)
    true = np.asarray([t["centre"] for t in truth], dtype=np.float64).reshape(-1, 3)
    true_r = np.asarray([t["radius"] for t in truth], dtype=np.float64)
    matches: list[int | None] = [None] * len(found)
    errors = []
    if len(found) and len(true):
        cost = np.linalg.norm(found[:, None] - true[None], axis=-1)
        rows, cols = linear_sum_assignment(cost)
        for r, c in zip(rows, cols):
            if cost[r, c] <= match_radii * true_r[c]:
                matches[r] = int(c)
                errors.append(float(cost[r, c]))
    return {
        "count": len(found), "count_gt": len(true), "matched": len(errors),
        "centroid_err_mean": float(np.mean(errors)) if errors else None,
        "centroid_err_median": float(np.median(errors)) if errors else None,
        "centroid_err_max": float(np.max(errors)) if errors else None,
        "match_radii": match_radii, "instance_match": matches,
    }


def ground_truth_file(folder: Path, class_name: str) -> Path | None:
    """The capture's ground-truth instances of a class: apples.json for apple, berries.json for berry."""
    stems = [f"{class_name}s", f"{class_name}es"] + ([f"{class_name[:-1]}ies"] if class_name.endswith("y") else [])
    for stem in stems:
        path = folder / f"{stem}.json"
        if path.exists():
            return path
    return None


# ------------------------------------------------------------------------------------------------ meshes


def reach_instances(class_occupancy, classes: list[str], reach: list[str], origin, voxel_size: float,
                    options: dict, gt_folder: Path | None) -> tuple[dict[str, list[dict]], dict[str, dict]]:
    """The instances (find_instances) of each reach class of the cache, and, where the capture has a
    ground-truth file for the class, their match against it (match_ground_truth; each instance gets
    its ground_truth_index)."""
    instances: dict[str, list[dict]] = {}
    ground_truth: dict[str, dict] = {}
    for name in reach:
        found = find_instances(np.asarray(class_occupancy[classes.index(name)], dtype=bool), origin, voxel_size,
                               options["min_instance_voxels"], options["split_min_radius_voxels"])
        for inst in found:
            inst["class"] = name
        instances[name] = found
        gt_file = ground_truth_file(gt_folder, name) if gt_folder else None
        if gt_file is not None:
            truth = json.loads(gt_file.read_text())
            result = match_ground_truth(found, truth, options["match_radii"])
            for inst, m in zip(found, result.pop("instance_match")):
                inst["ground_truth_index"] = m
            ground_truth[name] = {"file": str(gt_file), **result}
            log.info("%s: %d instances, %d in the ground truth, %d matched, mean centroid error %s",
                     name, result["count"], result["count_gt"], result["matched"], result["centroid_err_mean"])
    return instances, ground_truth


def class_mesh(occupied: np.ndarray, origin, voxel_size: float, max_triangles: int):
    """Marching cubes (level 0.5) on a (z, y, x) occupancy grid -> open3d TriangleMesh in world units,
    closed (the grid is padded), decimated to at most `max_triangles`; None when nothing is occupied."""
    import open3d as o3d
    from skimage.measure import marching_cubes

    if not np.any(occupied):
        return None
    padded = np.pad(np.asarray(occupied, dtype=np.float32), 1)
    verts_zyx, faces, _, _ = marching_cubes(padded, level=0.5)
    verts = np.asarray(origin, dtype=np.float64) + (verts_zyx[:, ::-1] - 1 + 0.5) * voxel_size
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts),
                                     o3d.utility.Vector3iVector(faces[:, ::-1].astype(np.int32)))
    if len(faces) > max_triangles:
        mesh = mesh.simplify_quadric_decimation(int(max_triangles))
    mesh.remove_unreferenced_vertices()
    mesh.compute_vertex_normals()
    return mesh


# ------------------------------------------------------------------------------------------------ stations


def approach_directions(outward: np.ndarray, elevations_deg=(0.0, 25.0, 50.0, -10.0),
                        azimuths_deg=(0.0, 30.0, -30.0, 60.0, -60.0, 90.0, -90.0, 135.0, -135.0, 180.0)) -> np.ndarray:
    """Unit vectors from a target toward candidate shoulders: around the horizontal `outward`
    direction (from the object's axis to the target), nearest to it first."""
    yaw0 = math.atan2(outward[1], outward[0])
    dirs = []
    for az in azimuths_deg:
        for el in elevations_deg:
            a, e = yaw0 + math.radians(az), math.radians(el)
            dirs.append([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
    return np.asarray(dirs)


def plan_station(target_sim: np.ndarray, target_radius_sim: float, clearance_fn, arm, centre_sim: np.ndarray,
                 approach_reach: float, floor_z: float | None) -> dict:
    """The station (lift position and yaw) with the widest straight approach corridor to a target.

    `clearance_fn(points_sim) -> distance (sim metres) to the nearest avoid matter`. The corridor is the
    segment from the fruit's surface to the shoulder; its clearance is the smallest distance along it.
    """
    outward = target_sim - centre_sim
    outward[2] = 0.0
    norm = np.linalg.norm(outward)
    outward = outward / norm if norm > 1e-9 else np.array([1.0, 0.0, 0.0])
    best = None
    t = np.linspace(0.0, 1.0, 48)[:, None]
    for u in approach_directions(outward):
        shoulder = target_sim + u * approach_reach * arm.reach
        base = shoulder - np.array([0.0, 0.0, arm.shoulder_height])
        if floor_z is not None and base[2] < floor_z:
            continue
        start = target_sim + u * (target_radius_sim + arm.max_radius)
        clearance = float(np.min(clearance_fn(start + t * (shoulder - start))))
        if best is None or clearance > best["corridor_clearance"] + 1e-9:
            yaw = math.atan2(-u[1], -u[0])
            best = {"base": base.tolist(), "yaw": yaw, "shoulder": shoulder.tolist(), "approach": (-u).tolist(),
                    "corridor_clearance": clearance}
    if best is None:  # every candidate is below the floor: stand on it
        u = outward
        shoulder = target_sim + u * approach_reach * arm.reach
        shoulder[2] = max(shoulder[2], floor_z + arm.shoulder_height)
        best = {"base": (shoulder - [0, 0, arm.shoulder_height]).tolist(), "yaw": math.atan2(-u[1], -u[0]),
                "shoulder": shoulder.tolist(), "approach": (-u).tolist(), "corridor_clearance": -1.0}
    best["reachable"] = bool(best["corridor_clearance"] > arm.max_radius)
    return best


# ------------------------------------------------------------------------------------------------ MJCF


def scene_mjcf(arm, meshes: dict[str, str], mesh_colours: dict[str, list], targets: list[dict],
               station: dict, bounds_sim: np.ndarray, timestep: float) -> str:
    """The MuJoCo scene: visual meshes, target sites, the arm (srfpipe.sim.arm) and an overview camera."""
    from srfpipe.sim.arm import actuators_mjcf, arm_mjcf

    centre = bounds_sim.mean(axis=0)
    extent = float(np.max(bounds_sim[1] - bounds_sim[0]))
    eye = centre + np.array([1.2, -1.2, 0.8]) * extent
    fwd = centre - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    assets = "\n    ".join(f'<mesh name="{name}" file="{path}"/>' for name, path in meshes.items())
    geoms = "\n    ".join(
        f'<geom name="mesh_{name}" type="mesh" mesh="{name}" contype="0" conaffinity="0" group="2" '
        f'rgba="{" ".join(f"{c:.3g}" for c in mesh_colours[name])}" mass="0"/>' for name in meshes)
    sites = "\n    ".join(
        f'<site name="target_{i}" pos="{" ".join(f"{v:.6g}" for v in t["centroid_sim"])}" '
        f'size="{t["radius_sim"]:.6g}" rgba="1 0.1 0.1 0.35" group="3"/>' for i, t in enumerate(targets))
    return f"""<mujoco model="srfpipe_scene">
  <!-- written by srfpipe package; the sim frame is the world frame scaled to metres (see scene.json) -->
  <compiler angle="radian" meshdir="."/>
  <option timestep="{timestep:.6g}" gravity="0 0 -9.81" integrator="implicitfast"/>
  <visual><global offwidth="640" offheight="480"/><quality shadowsize="1024"/>
    <headlight ambient="0.35 0.35 0.35" diffuse="0.5 0.5 0.5"/></visual>
  <asset>
    <texture name="sky" type="skybox" builtin="gradient" rgb1="0.62 0.76 0.95" rgb2="0.95 0.95 0.95" width="64" height="64"/>
    {assets}
  </asset>
  <worldbody>
    <light name="sun" directional="true" pos="0 0 {bounds_sim[1][2] + extent:.6g}" dir="0.3 0.2 -1"/>
    <camera name="overview" pos="{" ".join(f"{v:.6g}" for v in eye)}" xyaxes="{" ".join(f"{v:.6g}" for v in np.concatenate([right, up]))}" fovy="45"/>
    {geoms}
    {sites}
    {arm_mjcf(arm, station["base"], station["yaw"])}
  </worldbody>
  <actuator>
    {actuators_mjcf(arm)}
  </actuator>
</mujoco>
"""


# ------------------------------------------------------------------------------------------------ the stage


def read_ground_truth(images_path: Path | None) -> tuple[Path | None, dict | None]:
    """The capture's ground_truth/ folder that images.zarr (`images_path`) records, and its
    scene.json; (None, None) without an images.zarr, a recorded folder or its scene.json."""
    if images_path is None:
        return None, None
    from srfpipe.artifacts import meta, open_artifact

    folder = meta(open_artifact(images_path, stage="downscale")).get("ground_truth")
    if not folder or not (Path(folder) / "scene.json").exists():
        return None, None
    return Path(folder), json.loads((Path(folder) / "scene.json").read_text())


def _relative(target: Path, start: Path) -> str:
    import os

    return os.path.relpath(Path(target).resolve(), Path(start).resolve())


@dataclass
class SceneInputs:
    """What `package` reads of one scene: the occupancy cache (srfpipe distill), its classes and their
    roles, the world unit, and the capture's ground truth (read_ground_truth)."""

    group: object  # the occupancy.zarr group
    attrs: dict  # its srfpipe attributes
    grid: object  # srfpipe.occupancy.grid.VoxelGrid
    classes: list[str]
    avoid: list[str]
    reach: list[str]
    gt_folder: Path | None
    gt_scene: dict | None
    units: dict  # resolve_unit
    occupancy: np.ndarray  # (z, y, x) bool: all matter
    class_occupancy: np.ndarray  # (C, z, y, x) bool

    @property
    def metres_per_unit(self) -> float:
        return self.units["metres_per_unit"]

    @property
    def bounds_sim(self) -> np.ndarray:
        return np.asarray(self.grid.bounds_world) * self.metres_per_unit


def read_scene(occupancy_path: Path, srf_path: Path | None, options: dict, images_path=None) -> SceneInputs:
    """Open the occupancy cache (checked; the trained field's artifact too, when given: the runtime
    renders from it), its classes and roles (avoid / reach), the capture's ground truth and the unit."""
    from srfpipe.artifacts import meta, open_artifact, recorded_input, require_input
    from srfpipe.occupancy.cache import check_cache

    group = open_artifact(occupancy_path, stage="distill")
    attrs = meta(group)
    if srf_path is not None:  # checked: the runtime renders from it (without it: contact only, no views)
        open_artifact(srf_path, stage="train")
        # one scene: the field the cache was distilled from, and the images that field was trained on
        require_input(occupancy_path, srf_path, "train")
        if images_path is not None:
            require_input(srf_path, images_path, "downscale")
    elif images_path is not None and (field := recorded_input(occupancy_path, "train")) is not None and field.exists():
        # no field given: the images must still be the ones the cache's field was trained on
        require_input(field, images_path, "downscale")
    grid = check_cache(occupancy_path, group, attrs)  # after the inputs: the wrong scene is the clearer error
    roles = dict(zip(attrs["distance"]["classes"], attrs["distance"]["roles"]))
    gt_folder, gt_scene = read_ground_truth(Path(images_path) if images_path else None)
    units = resolve_unit(options, attrs.get("unit"), gt_scene)
    return SceneInputs(group, attrs, grid, list(attrs["classes"]),
                       [c for c, r in roles.items() if r == "avoid"], [c for c, r in roles.items() if r == "reach"],
                       gt_folder, gt_scene, units, np.asarray(group["occupancy"][...], dtype=bool),
                       np.asarray(group["class_occupancy"][...], dtype=bool))


def contact_field(scene: SceneInputs) -> tuple[dict[str, np.ndarray], dict]:
    """The signed distance fields contact uses (world units, by name) and the manifest's entry for
    them: the cache's fields of the avoid classes, or, in a scene without an avoid class, the distance
    to all occupied space (signed_distance_field; written to contact.zarr)."""
    from srfpipe.occupancy.distill import signed_distance_field

    distance = scene.attrs["distance"]
    if scene.avoid:
        fields = {c: np.asarray(scene.group["distance"][distance["classes"].index(c)]) for c in scene.avoid}
        return fields, {"kind": "occupancy.zarr distance", "classes": scene.avoid}
    trunc = float(distance["truncation"])
    return ({"occupied": signed_distance_field(scene.occupancy, scene.grid, trunc)},
            {"kind": "contact.zarr distance", "classes": ["occupied"], "truncation": trunc})


def clearance_function(fields: dict[str, np.ndarray], grid, metres_per_unit: float):
    """`clearance(points_sim) -> (N,)`: sim metres from each point to the nearest matter of `fields`
    (signed distances in world units on `grid`, sampled trilinearly; the smallest of them)."""
    from srfpipe.occupancy import kernels

    s = metres_per_unit
    origin = np.asarray(grid.origin, np.float64)
    arrays = [np.ascontiguousarray(field, np.float32) for field in fields.values()]

    def clearance(points_sim: np.ndarray) -> np.ndarray:
        pts = np.ascontiguousarray(np.asarray(points_sim, dtype=np.float64) / s)
        best = np.full(len(pts), np.inf)
        for field in arrays:
            d, grad = np.empty(len(pts)), np.empty((len(pts), 3))
            kernels.distance_gradient(pts, field, origin, grid.voxel_size, d, grad)
            best = np.minimum(best, d)
        return best * s

    return clearance


def find_targets(scene: SceneInputs, options: dict) -> tuple[dict[str, list[dict]], dict[str, dict], list[dict]]:
    """The instances of each reach class and their ground-truth match (reach_instances), with their
    centroid and radius in sim metres; the targets are all of them, in the order of the reach classes."""
    instances, ground_truth = reach_instances(scene.class_occupancy, scene.classes, scene.reach, scene.grid.origin,
                                              scene.grid.voxel_size, options, scene.gt_folder)
    s = scene.metres_per_unit
    for inst in (inst for found in instances.values() for inst in found):
        inst["centroid_sim"] = (np.asarray(inst["centroid"]) * s).tolist()
        inst["radius_sim"] = inst["radius"] * s
    return instances, ground_truth, [inst for name in scene.reach for inst in instances[name]]


def place_arm(targets: list[dict], bounds_sim: np.ndarray, options: dict, clearance):
    """The arm (ArmSpec), sized to the scene, and the station the MJCF places it at. Each target gets
    its `station` (plan_station); the arm stands at the first reachable target's station, else (no
    target, or none reachable) faces the object's centre from outside its box."""
    from srfpipe.sim.arm import ArmSpec

    extent_sim = float(np.max(bounds_sim[1] - bounds_sim[0]))
    reach_m = options["arm_reach"] if options["arm_reach"] is not None else options["arm_reach_fraction"] * extent_sim
    arm = ArmSpec(reach=float(reach_m), wrist_fovy_deg=options["wrist_fovy_deg"])
    centre_sim = bounds_sim.mean(axis=0)
    floor_z = float(bounds_sim[0][2]) if options["floor"] == "bounds_min_z" else None
    for inst in targets:
        inst["station"] = plan_station(np.asarray(inst["centroid_sim"]), inst["radius_sim"], clearance, arm,
                                       centre_sim, options["approach_reach"], floor_z)
    first = next((t["station"] for t in targets if t["station"]["reachable"]), None)
    if first is None:
        side = centre_sim + np.array([0.5 * (bounds_sim[1][0] - bounds_sim[0][0]) + 0.5 * arm.reach, 0.0, 0.0])
        side[2] = max(centre_sim[2], (floor_z if floor_z is not None else -np.inf) + arm.shoulder_height)
        first = {"base": (side - [0, 0, arm.shoulder_height]).tolist(), "yaw": math.pi}
    return arm, first


def write_meshes(folder: Path, scene: SceneInputs, max_triangles: int) -> tuple[dict, dict, dict]:
    """meshes/{name}.ply (world units) and .stl (sim metres) of all matter (`occupied`) and of each
    class (class_mesh). Returns the MJCF's mesh files and RGBA colours by name (a class in its colour
    of the eval renders, evaluate.class_rgba) and the manifest's mesh entries."""
    import open3d as o3d

    from srfpipe.evaluate import class_rgba

    (folder / "meshes").mkdir()
    meshes, colours, mesh_info = {}, {}, {}
    rgba = class_rgba(scene.classes)
    named = [("occupied", scene.occupancy)] + [(c, scene.class_occupancy[i]) for i, c in enumerate(scene.classes)]
    for name, occ in named:
        mesh = class_mesh(occ, scene.grid.origin, scene.grid.voxel_size, max_triangles)
        if mesh is None:
            continue
        o3d.io.write_triangle_mesh(str(folder / "meshes" / f"{name}.ply"), mesh)
        sim_mesh = o3d.geometry.TriangleMesh(mesh).scale(scene.metres_per_unit, center=np.zeros(3))
        sim_mesh.compute_triangle_normals()
        o3d.io.write_triangle_mesh(str(folder / "meshes" / f"{name}.stl"), sim_mesh)
        meshes[name] = f"meshes/{name}.stl"
        colours[name] = rgba[name] if name in scene.classes else [0.55, 0.5, 0.45, 1.0]
        mesh_info[name] = {"ply": f"meshes/{name}.ply", "stl": f"meshes/{name}.stl",
                           "triangles": len(mesh.triangles), "vertices": len(mesh.vertices)}
    if scene.classes:  # with classes, `occupied` would hide them: show it only as a faint shell
        colours["occupied"] = [0.55, 0.5, 0.45, 0.12]
    return meshes, colours, mesh_info


def write_fields(folder: Path, scene: SceneInputs, distance: dict, contact: dict, srf_path, field, options) -> bool:
    """baked.zarr, the field sampled on the cache's grid (srfpipe.sim.baked), when there is a field:
    the trained one at `srf_path`, or `field`; contact.zarr, the distance to all occupied space, when
    the scene has no avoid class. Returns whether baked.zarr was written."""
    if srf_path is not None or field is not None:
        from srfpipe.sim.baked import bake, write_baked

        if field is None:
            from srfpipe.srf.query import SemanticRadianceField

            field = SemanticRadianceField.load(srf_path, device=options["device"])
        # a cache written before the key existed was distilled at today's default
        floor = float(scene.attrs["config"].get("density_floor_alpha", OccupancySettings.density_floor_alpha))
        write_baked(folder / "baked.zarr", bake(field, scene.grid, scene.group["probability"][...], floor),
                    scene.attrs["grid"])
    if not scene.avoid:
        import zarr

        store = zarr.open_group(str(folder / "contact.zarr"), mode="w")
        shape = scene.grid.shape
        store.create_array("distance", shape=shape, dtype=np.float32, chunks=shape)[...] = distance["occupied"]
        store.attrs["srfpipe"] = {"grid": scene.attrs["grid"], "signed": "negative inside, world units",
                                  "truncation": contact["truncation"]}
    return srf_path is not None or field is not None


def manifest_task(targets: list[dict], classes: list[str], reach: list[str], options: dict) -> dict:
    """The manifest's task (None without targets) and the note that says why there is none."""
    task = None if not targets else {
        "kind": "reach", "classes": reach, "targets": len(targets),
        "reachable_targets": [i for i, t in enumerate(targets) if t["station"]["reachable"]],
        "success_margin": options["success_margin"],
    }
    note = None if targets else (
        "no reach class in this scene (classes %s, occupancy.reach): geometry and contact only" % classes
        if not reach else "no instance of the reach classes %s was found: geometry and contact only" % reach)
    return {"task": task, "note": note}


def manifest_frames(gt_scene: dict | None, metres_per_unit: float) -> dict:
    """The manifest's frames: world (the capture's), sim (MuJoCo's: the world scaled to metres), cameras."""
    s = metres_per_unit
    return {
        "world": (gt_scene or {}).get("world_frame", "the capture's world frame (z up assumed for gravity)"),
        "sim": "MuJoCo frame: the world frame scaled by metres_per_unit (same origin and axes)",
        "sim_from_world": np.diag([s, s, s, 1.0]).tolist(),
        "up": "+z",
        "cameras": "SRF renders take OpenCV camera_to_world in world units; MuJoCo cameras look along "
                   "their -z with +y up: camera_to_world_cv = camera_to_world_mujoco @ diag(1, -1, -1, 1)",
    }


def scene_manifest(folder: Path, scene: SceneInputs, options: dict, inputs: tuple, out_path: Path, targets: list[dict],
                   instances: dict, ground_truth: dict, arm, mesh_info: dict, contact: dict, baked: bool) -> dict:
    """scene.json (see the module docstring); `inputs` (occupancy, srf, images paths, None where not
    given), `folder` the package being written: its files (but the zarr stores) with their sha256."""
    import mujoco

    from srfpipe.artifacts import file_sha256, provenance

    occupancy_path, srf_path, _ = inputs
    files = {p.relative_to(folder).as_posix(): file_sha256(p) for p in sorted(folder.rglob("*"))
             if p.is_file() and not {"contact.zarr", "baked.zarr"} & set(p.parts)}
    units = scene.units
    return {
        "format": MANIFEST_FORMAT,
        "srfpipe": provenance(STAGE, options, [p for p in inputs if p], complete=True),
        "classes": scene.classes,
        "roles": {"avoid": scene.avoid, "reach": scene.reach},
        **manifest_task(targets, scene.classes, scene.reach, options),
        "units": {**units, "world": units["unit"] or "unknown", "sim": "metre"},
        "frames": manifest_frames(scene.gt_scene, scene.metres_per_unit),
        "bounds_world": np.asarray(scene.grid.bounds_world).tolist(),
        "bounds_sim": scene.bounds_sim.tolist(),
        "voxel_size_world": scene.grid.voxel_size,
        "field": {"srf": _relative(srf_path, out_path) if srf_path else None, "baked": "baked.zarr" if baked else None,
                  "occupancy": _relative(occupancy_path, out_path), "contact": contact},
        "arm": arm.describe(),
        "mjcf": "scene.xml",
        "meshes": mesh_info,
        "instances": {name: len(found) for name, found in instances.items()},
        "ground_truth": ground_truth or None,
        "files": files,
        "versions": {**package_versions_now(), "mujoco": mujoco.__version__},
    }


def package(occupancy_path, srf_path, out_path, options: dict, images_path=None, field=None) -> Path:
    """Write the simulator package for one scene (see the module docstring). Returns `out_path`.

    `srf_path` None packages a cache without a trained field: contact works, and renders too when
    `field` is given (an object with density, radiance and background, e.g. an AnalyticField whose
    cache this is), else not. The steps: read the cache (read_scene), the contact field
    (contact_field), the targets and the arm's stations (find_targets, place_arm), then, in a hidden
    sibling renamed when complete, the meshes and the MJCF (write_meshes, scene_mjcf), the sampled
    fields (write_fields), targets.json and the manifest (scene_manifest)."""
    import mujoco

    from srfpipe.artifacts import atomic_directory

    occupancy_path, out_path = Path(occupancy_path), Path(out_path)
    srf_path = Path(srf_path) if srf_path is not None else None
    scene = read_scene(occupancy_path, srf_path, options, images_path)
    distance, contact = contact_field(scene)
    instances, ground_truth, targets = find_targets(scene, options)
    clearance = clearance_function(distance, scene.grid, scene.metres_per_unit)
    arm, station = place_arm(targets, scene.bounds_sim, options, clearance)

    with atomic_directory(out_path) as tmp:
        meshes, colours, mesh_info = write_meshes(tmp, scene, options["mesh_max_triangles"])
        xml = scene_mjcf(arm, meshes, colours, targets, station, scene.bounds_sim, options["timestep"])
        (tmp / "scene.xml").write_text(xml)
        baked = write_fields(tmp, scene, distance, contact, srf_path, field, options)
        mujoco.MjModel.from_xml_path(str(tmp / "scene.xml"))  # the MJCF must load before the package is visible
        (tmp / "targets.json").write_text(json.dumps(targets, indent=1) + "\n")
        manifest = scene_manifest(tmp, scene, options, (occupancy_path, srf_path, images_path), out_path,
                                  targets, instances, ground_truth, arm, mesh_info, contact, baked)
        (tmp / "scene.json").write_text(json.dumps(manifest, indent=1) + "\n")
    return out_path


def package_versions_now() -> dict:
    from srfpipe.artifacts import package_versions

    return package_versions()


def add_arguments(parser) -> None:
    from srfpipe.config import add_options_arguments

    parser.add_argument("--occupancy", required=True, metavar="ZARR", help="occupancy cache (occupancy.zarr from `srfpipe distill`)")
    parser.add_argument("--srf", required=True, metavar="ZARR", help="trained field the runtime renders from (srf.zarr)")
    parser.add_argument("--images", metavar="ZARR", help="images.zarr: its ground truth (if any) is matched against the instances")
    parser.add_argument("--out", required=True, metavar="DIR", help="package folder to write (sim/)")
    parser.add_argument("--threads", type=int, default=2, help="CPU threads for sampling the field")
    add_options_arguments(parser, "sim")


def run(args) -> int:
    import torch

    from srfpipe.config import stage_options

    torch.set_num_threads(max(1, args.threads))
    options = stage_options(args, "sim")
    for name in ("occupancy", "srf") + (("images",) if args.images else ()):
        if not Path(getattr(args, name)).exists():
            raise FileNotFoundError(f"{getattr(args, name)}: --{name} does not exist")
    package(args.occupancy, args.srf, args.out, options, images_path=args.images)
    return 0
