"""The simulator loop of the paper's Fig. 2 on a package (results/{scene}/sim/):

    sim = Simulator("results/orchard/sim")
    sim.reset(target=0)                       # the lift at target 0's station, the arm at home
    out = sim.step(sim.data.ctrl + delta)     # MuJoCo advances; contact from the occupancy cache
    view = sim.render_wrist()                 # SRF Render(P) from the wrist camera: rgb, semantic, depth

* MuJoCo moves the arm (position servos) and gives the wrist camera pose and the link transforms.
* The SRF renders RGB, the per-class semantic map and depth from the wrist camera's pose (OpenCV
  convention, world units): by default from the field baked onto the cache's grid
  (`renderer="baked"`, srfpipe.sim.baked, tens of renders per second on a CPU), or from the network
  itself (`renderer="field"`, srfpipe.srf.query: exact, a few per second on a CPU).
* The occupancy cache gives contact: every link capsule (segment + radius) against the signed
  distance to the avoid classes (or, in a scene without classes, to all occupied space): clearance
  = d(axis point) - radius, penetration = max(0, -clearance), and the distance gradient (pointing
  away from the matter) at the deepest point. Distances are sampled on each capsule's axis at
  spacing <= half its radius, exact to about half a voxel (the cache's resolution).

The sim frame is the world frame scaled to metres (`metres_per_unit` in scene.json); everything this
module returns is in sim metres unless it says world.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from srfpipe.sim.arm import JOINTS, LINKS

# MuJoCo cameras look along -z with +y up; OpenCV along +z with +y down
MUJOCO_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def default_gl_backend() -> str:
    """Headless MuJoCo rendering: EGL (Debian libegl1 + libegl-mesa0 + libgl1-mesa-dri) unless set.
    It takes effect only before mujoco is first imported: srfpipe.sim's __init__ sets it."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    return os.environ["MUJOCO_GL"]


@dataclass
class Contact:
    """Capsule-vs-occupancy contact for all links (sim metres)."""

    in_contact: bool
    penetration: float  # max over links of max(0, -clearance)
    clearance: np.ndarray  # (links,) smallest d - radius on each link
    gradient: np.ndarray  # (3,) unit distance gradient at the closest point (away from matter), 0 when clipped
    closest_link: int
    closest_point: np.ndarray  # (3,) sim point on the closest link's axis
    link_gradients: np.ndarray  # (links, 3) gradient at each link's closest point


class DistanceFields:
    """Signed distance fields (world units) on one voxel grid, queried in sim metres."""

    def __init__(self, fields: dict[str, np.ndarray], origin, voxel_size: float, metres_per_unit: float):
        self.names = list(fields)
        # the distance to a union of classes is the smallest of their distances: one field to query
        self.field = (np.ascontiguousarray(np.minimum.reduce([np.asarray(v, np.float32) for v in fields.values()]))
                      if fields else None)
        self.origin = np.asarray(origin, dtype=np.float64)
        self.voxel_size = float(voxel_size)
        self.s = float(metres_per_unit)

    def query(self, points_sim: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Smallest signed distance over the fields (sim metres) and its gradient, at (M, 3) points."""
        from srfpipe.occupancy import kernels

        pts = np.ascontiguousarray(np.asarray(points_sim, dtype=np.float64) / self.s)
        if not np.all(np.isfinite(pts)):
            raise ValueError("contact query: link positions are not finite (the simulation diverged)")
        d = np.full(len(pts), np.inf)
        grad = np.zeros((len(pts), 3))
        if self.field is not None:
            kernels.distance_gradient_serial(pts, self.field, self.origin, self.voxel_size, d, grad)
        return d * self.s, grad


def capsule_contact(fields: DistanceFields, starts: np.ndarray, ends: np.ndarray, radii: np.ndarray,
                    samples: np.ndarray) -> Contact:
    """Contact of capsules (start, end, radius; sim metres) with the matter of `fields`.

    `samples[i]` is the number of points on capsule i's axis (>= 2). One batched distance query.
    """
    starts, ends, radii = np.asarray(starts, float), np.asarray(ends, float), np.asarray(radii, float)
    owner = np.repeat(np.arange(len(radii)), samples)
    t = np.concatenate([np.linspace(0.0, 1.0, int(n)) for n in samples])
    points = starts[owner] + t[:, None] * (ends[owner] - starts[owner])
    d, grad = fields.query(points)
    clearance_pts = d - radii[owner]
    n = len(radii)
    clearance = np.full(n, np.inf)
    arg = np.zeros(n, dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(samples)])
    for i in range(n):  # links are few; the points were queried in one batch
        seg = clearance_pts[offsets[i]:offsets[i + 1]]
        j = int(np.argmin(seg))
        clearance[i], arg[i] = seg[j], offsets[i] + j
    k = int(np.argmin(clearance))
    link_gradients = grad[arg]
    return Contact(in_contact=bool(clearance[k] < 0.0), penetration=float(max(0.0, -clearance[k])),
                   clearance=clearance, gradient=link_gradients[k].copy(), closest_link=k,
                   closest_point=points[arg[k]].copy(), link_gradients=link_gradients)


def load_manifest(package_dir) -> dict:
    path = Path(package_dir) / "scene.json"
    if not path.exists():
        raise FileNotFoundError(f"{package_dir}: not a simulator package (no scene.json; run `srfpipe package`)")
    manifest = json.loads(path.read_text())
    if manifest.get("format") != "srfpipe-sim-1":
        raise ValueError(f"{path}: unknown package format {manifest.get('format')!r}")
    return manifest


class Simulator:
    """MuJoCo + SRF + occupancy cache for one package. See the module docstring."""

    def __init__(self, package_dir, device: str = "cpu", wrist_size: tuple[int, int] = (64, 64),
                 control_dt: float = 0.04, renderer: str = "baked", threads: int = 1):
        import mujoco

        self.package = Path(package_dir)
        self.manifest = load_manifest(self.package)
        self.s = float(self.manifest["units"]["metres_per_unit"])
        self.model = mujoco.MjModel.from_xml_path(str(self.package / self.manifest["mjcf"]))
        self.data = mujoco.MjData(self.model)
        self.substeps = max(1, int(round(control_dt / self.model.opt.timestep)))
        self.control_dt = self.substeps * self.model.opt.timestep
        self.device = device
        if renderer not in ("baked", "field"):
            raise ValueError(f"renderer must be 'baked' or 'field', got {renderer!r}")
        self.renderer = renderer
        self.threads = threads
        self._baked = None
        self.wrist_size = (int(wrist_size[0]), int(wrist_size[1]))  # width, height
        self.targets = json.loads((self.package / "targets.json").read_text())
        self.classes = list(self.manifest["classes"])
        self.arm = self.manifest["arm"]
        self.home = np.asarray(self.arm["home"], dtype=np.float64)
        name = mujoco.mj_name2id
        obj = mujoco.mjtObj
        self.joint_ids = np.array([name(self.model, obj.mjOBJ_JOINT, j) for j in JOINTS])
        self.qpos_adr = self.model.jnt_qposadr[self.joint_ids]
        self.dof_adr = self.model.jnt_dofadr[self.joint_ids]
        self.link_geoms = np.array([name(self.model, obj.mjOBJ_GEOM, g) for g in LINKS])
        self.tip_site = name(self.model, obj.mjOBJ_SITE, "tip")
        self.wrist_camera = name(self.model, obj.mjOBJ_CAMERA, "wrist")
        self.mocap = self.model.body_mocapid[name(self.model, obj.mjOBJ_BODY, "base")]
        self.ctrl_range = self.model.actuator_ctrlrange.copy()
        radii = self.model.geom_size[self.link_geoms, 0]
        half = self.model.geom_size[self.link_geoms, 1]
        self.link_radii = radii.copy()
        self.link_samples = np.maximum(2, np.ceil(2 * half / (0.5 * radii)).astype(np.int64) + 1)
        self.fields = self._distance_fields()
        self._srf = None
        self.station = None
        self.reset()

    # ------------------------------------------------------------------ loading

    def _distance_fields(self) -> DistanceFields:
        from srfpipe.occupancy.grid import VoxelGrid

        contact = self.manifest["field"]["contact"]
        if contact["kind"] == "contact.zarr distance":
            import zarr

            group = zarr.open_group(str(self.package / "contact.zarr"), mode="r")
            grid = VoxelGrid.from_attrs(dict(group.attrs["srfpipe"])["grid"])
            return DistanceFields({"occupied": group["distance"][...]}, grid.origin, grid.voxel_size, self.s)
        cache = self.cache
        return DistanceFields({c: cache.distance_field(c) for c in contact["classes"]}, cache.grid.origin,
                              cache.voxel_size, self.s)

    @property
    def cache(self):
        if not hasattr(self, "_cache"):
            from srfpipe.occupancy import OccupancyCache

            self._cache = OccupancyCache.load(self.package / self.manifest["field"]["occupancy"])
        return self._cache

    @property
    def srf(self):
        if self._srf is None:
            from srfpipe.srf.query import SemanticRadianceField

            path = self.manifest["field"].get("srf")
            if path is None:
                raise ValueError(f"{self.package}: this package has no field to render (packaged without srf.zarr)")
            self._srf = SemanticRadianceField.load(self.package / path, device=self.device)
        return self._srf

    @property
    def baked(self):
        if self._baked is None:
            from srfpipe.sim.baked import BakedRenderer

            path = self.manifest["field"].get("baked")
            if path is None:
                raise ValueError(f"{self.package}: this package has no field to render (packaged without srf.zarr)")
            self._baked = BakedRenderer(self.package / path, threads=self.threads)
        return self._baked

    # ------------------------------------------------------------------ state

    def reset(self, target: int | None = None, qpos=None) -> None:
        """Arm at `qpos` (default home), lift at the station of `target` (default: as in the MJCF)."""
        import mujoco

        mujoco.mj_resetData(self.model, self.data)
        if target is not None:
            station = self.targets[target]["station"]
            self.data.mocap_pos[self.mocap] = station["base"]
            yaw = station["yaw"]
            self.data.mocap_quat[self.mocap] = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
            self.station = station
        q = self.home if qpos is None else np.asarray(qpos, dtype=np.float64)
        self.data.qpos[self.qpos_adr] = q
        self.data.ctrl[:] = np.clip(q, self.ctrl_range[:, 0], self.ctrl_range[:, 1])
        mujoco.mj_forward(self.model, self.data)

    @property
    def qpos(self) -> np.ndarray:
        return self.data.qpos[self.qpos_adr].copy()

    @property
    def qvel(self) -> np.ndarray:
        return self.data.qvel[self.dof_adr].copy()

    def tip(self) -> np.ndarray:
        return self.data.site_xpos[self.tip_site].copy()

    def step(self, ctrl) -> Contact:
        """Set the joint targets (clipped to the ranges), advance `control_dt`, return the contact."""
        import mujoco

        ctrl = np.asarray(ctrl, dtype=np.float64)
        if not np.all(np.isfinite(ctrl)):
            raise ValueError(f"joint targets must be finite, got {ctrl}")
        self.data.ctrl[:] = np.clip(ctrl, self.ctrl_range[:, 0], self.ctrl_range[:, 1])
        mujoco.mj_step(self.model, self.data, nstep=self.substeps)
        return self.contact()

    # ------------------------------------------------------------------ queries

    def link_segments(self) -> tuple[np.ndarray, np.ndarray]:
        """Each link capsule's axis end points (sim metres), from MuJoCo's geom frames."""
        centre = self.data.geom_xpos[self.link_geoms]
        axis = self.data.geom_xmat[self.link_geoms].reshape(-1, 3, 3)[:, :, 2]
        half = self.model.geom_size[self.link_geoms, 1][:, None]
        return centre - axis * half, centre + axis * half

    def contact(self) -> Contact:
        starts, ends = self.link_segments()
        return capsule_contact(self.fields, starts, ends, self.link_radii, self.link_samples)

    def wrist_pose_world(self) -> np.ndarray:
        """camera_to_world of the wrist camera, OpenCV convention, world units (for the SRF)."""
        pose = np.eye(4)
        pose[:3, :3] = self.data.cam_xmat[self.wrist_camera].reshape(3, 3)
        pose[:3, 3] = self.data.cam_xpos[self.wrist_camera] / self.s
        return pose @ MUJOCO_TO_OPENCV

    def wrist_intrinsics(self) -> np.ndarray:
        width, height = self.wrist_size
        fy = 0.5 * height / math.tan(math.radians(self.model.cam_fovy[self.wrist_camera]) / 2)
        return np.array([fy, fy, width / 2, height / 2])

    def render_wrist(self) -> dict:
        """Render(P) from the wrist camera: rgb (H, W, 3), semantic (H, W, C) in [0, 1], depth (H, W) in
        sim metres (distance along each ray), accumulation."""
        width, height = self.wrist_size
        source = self.baked if self.renderer == "baked" else self.srf
        out = source.render(self.wrist_pose_world(), self.wrist_intrinsics(), width, height)
        return {"rgb": out["rgb"], "semantic": out["semantic"], "depth": out["depth"] * self.s,
                "accumulation": out["accumulation"]}

    def tip_jacobian(self) -> np.ndarray:
        """(3, joints) positional Jacobian of the tool tip (sim metres per radian)."""
        import mujoco

        jacp = np.zeros((3, self.model.nv))
        mujoco.mj_jacSite(self.model, self.data, jacp, None, self.tip_site)
        return jacp[:, self.dof_adr]

    def point_jacobian(self, point: np.ndarray, link: int) -> np.ndarray:
        """(3, joints) Jacobian of a point fixed to link `link` (index into LINKS)."""
        import mujoco

        jacp = np.zeros((3, self.model.nv))
        body = self.model.geom_bodyid[self.link_geoms[link]]
        mujoco.mj_jac(self.model, self.data, jacp, None, np.asarray(point, dtype=np.float64), body)
        return jacp[:, self.dof_adr]


class ThirdPersonCamera:
    """MuJoCo's offscreen renderer (headless: EGL by default, see `default_gl_backend`) on a free
    camera looking at a point from a distance; the target sites are drawn (geom group 3)."""

    def __init__(self, sim: Simulator, height: int = 240, width: int = 320):
        import mujoco

        default_gl_backend()
        self.sim = sim
        self.renderer = mujoco.Renderer(sim.model, height, width)
        self.camera = mujoco.MjvCamera()
        self.options = mujoco.MjvOption()
        self.options.geomgroup[3] = 1

    def render(self, lookat, distance: float, azimuth_deg: float, elevation_deg: float = -20.0) -> np.ndarray:
        self.camera.lookat[:] = np.asarray(lookat, dtype=np.float64)
        self.camera.distance = float(distance)
        self.camera.azimuth = float(azimuth_deg)
        self.camera.elevation = float(elevation_deg)
        self.renderer.update_scene(self.sim.data, camera=self.camera, scene_option=self.options)
        return self.renderer.render().copy()

    def close(self) -> None:
        self.renderer.close()
