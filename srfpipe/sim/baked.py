"""The SRF baked onto the occupancy grid, for wrist renders at simulation rate on a CPU.

The network renders a 64 x 64 view in a few hundred milliseconds on 2 CPU cores; the loop needs tens
per second. So the package stage samples the field once on the cache's voxel grid (like SNeRG's or
Plenoxels' baking): sigma at every voxel centre, the emitted colour where the voxel's opacity reaches
`density_floor_alpha` (the mean over the 6 axis view directions: view dependence is dropped), the
cache's per-class probabilities, and the field's background (sky colour as a 32 x 64 latitude-longitude
map, background class probabilities). `render` then evaluates the paper's Eq. 1 and 3 on that grid:

    C(r) = sum_k T_k alpha_k c_k + T_K c_bg,   S(r) = sum_k T_k alpha_k p_k + T_K p_bg,
    alpha_k = 1 - exp(-sigma_k delta),  T_k = prod_{j<k} (1 - alpha_j)

marching each ray in steps of one voxel (`STEP_VOXELS`) with trilinear sigma (colour and probabilities interpolated
with sigma-weighted trilinear weights), skipping empty 8^3 blocks, stopping when T < 1e-3. One numba
pass over the rays. The semantic map composites probabilities (the network composites logits, then
applies the sigmoid): the two agree where a ray meets one surface; `benchmarks/sim.py` measures how
far the baked renders are from the network's.

baked.zarr: `density` (Z, Y, X) float32 per world unit, `rgb` (Z, Y, X, 3) uint8, `probability`
(Z, Y, X, C) uint8, `blocks` (bz, by, bx) uint8, `background` (32, 64, 3) uint8; attrs: grid, block,
background_probability, density_floor_alpha, view_directions.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

# march's numba cache does not see an edit of this inlined helper: touch this file after one
from srfpipe.occupancy.kernels import axis_corners

BLOCK = 8
# One voxel per step: on the demo orchard's package the 64 x 64 wrist views differ from half-voxel
# steps by 54 dB PSNR, and render 1.6x faster (14.5 vs 9.1 Hz on one thread).
STEP_VOXELS = 1.0
PARALLEL_CHUNK_RAYS = 64
ENV_SHAPE = (32, 64)  # latitude (z from +1 to -1) x longitude (atan2(y, x) from -pi to pi)


def env_directions(shape=ENV_SHAPE) -> np.ndarray:
    """Unit world directions at the centres of a latitude-longitude map (h, w, 3), +z up."""
    h, w = shape
    theta = (np.arange(h) + 0.5) / h * np.pi  # from +z down
    phi = (np.arange(w) + 0.5) / w * 2 * np.pi - np.pi
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    return np.stack([st * np.cos(phi)[None], st * np.sin(phi)[None], np.broadcast_to(ct, (h, w))], axis=-1)


def bake(srf, grid, probability_chw: np.ndarray, density_floor_alpha: float = 0.001,
         batch: int = 1 << 18) -> dict:
    """Sample the field on `grid` (srfpipe.occupancy.VoxelGrid). probability_chw: the cache's (C, Z, Y, X)."""
    nz, ny, nx = grid.shape
    v = grid.voxel_size
    density = np.zeros(grid.shape, dtype=np.float32)
    for k in range(0, nz, max(1, batch // (ny * nx))):
        zs = slice(k, min(nz, k + max(1, batch // (ny * nx))))
        centres = grid.voxel_centres((zs, slice(0, ny), slice(0, nx)))
        density[zs] = srf.density(centres.reshape(-1, 3)).reshape(centres.shape[:3])
    floor = -math.log(1.0 - density_floor_alpha) / v
    density[density < floor] = 0.0
    rgb = np.zeros(grid.shape + (3,), dtype=np.uint8)
    kji = np.argwhere(density > 0)
    views = np.concatenate([np.eye(3), -np.eye(3)])
    for start in range(0, len(kji), batch // len(views)):
        part = kji[start:start + batch // len(views)]
        centres = np.asarray(grid.origin) + (part[:, ::-1] + 0.5) * v
        points = np.repeat(centres, len(views), axis=0)
        dirs = np.tile(views, (len(part), 1))
        colour = srf.radiance(points, dirs).reshape(len(part), len(views), 3).mean(axis=1)
        rgb[tuple(part.T)] = np.clip(np.round(colour * 255), 0, 255).astype(np.uint8)
    env_rgb, bg_prob = srf.background(env_directions().reshape(-1, 3))
    background = np.clip(np.round(env_rgb.reshape(ENV_SHAPE + (3,)) * 255), 0, 255).astype(np.uint8)
    probability = np.ascontiguousarray(np.moveaxis(np.asarray(probability_chw, dtype=np.uint8), 0, -1))
    return {"density": density, "rgb": rgb, "probability": probability, "blocks": occupied_blocks(density),
            "background": background, "background_probability": bg_prob.astype(np.float64).tolist(),
            "density_floor_alpha": density_floor_alpha, "view_directions": 6}


def occupied_blocks(density: np.ndarray, block: int = BLOCK) -> np.ndarray:
    """1 for every block^3 block a trilinear lookup can see non-zero density in (dilated by a voxel)."""
    from scipy.ndimage import maximum_filter

    any_density = maximum_filter((density > 0).astype(np.uint8), size=3, mode="constant")
    shape = [math.ceil(n / block) for n in density.shape]
    padded = np.zeros([s * block for s in shape], dtype=np.uint8)
    padded[:density.shape[0], :density.shape[1], :density.shape[2]] = any_density
    return padded.reshape(shape[0], block, shape[1], block, shape[2], block).max(axis=(1, 3, 5))


def write_baked(path, baked: dict, grid_attrs: dict) -> None:
    import zarr

    group = zarr.open_group(str(path), mode="w")
    for name in ("density", "rgb", "probability", "blocks", "background"):
        array = baked[name]
        chunks = array.shape if array.ndim < 3 else (min(32, array.shape[0]),) + array.shape[1:]
        group.create_array(name, shape=array.shape, dtype=array.dtype, chunks=chunks)[...] = array
    group.attrs["srfpipe"] = {"grid": grid_attrs, "block": BLOCK,
                              **{k: baked[k] for k in ("background_probability", "density_floor_alpha", "view_directions")}}


@njit(parallel=True, cache=True, nogil=True)
def march(origins, dirs, density, rgb, prob, blocks, block, grid_origin, voxel, near, far, env, bg_prob,
          out_rgb, out_sem, out_depth, out_acc):
    """Volume-render rays (world units) through the baked grid; see the module docstring."""
    nz, ny, nx = density.shape
    n_classes = prob.shape[3]
    env_h, env_w = env.shape[0], env.shape[1]
    step = STEP_VOXELS * voxel
    lo0, lo1, lo2 = grid_origin[0], grid_origin[1], grid_origin[2]
    hi0, hi1, hi2 = lo0 + nx * voxel, lo1 + ny * voxel, lo2 + nz * voxel
    for r in prange(origins.shape[0]):
        o0, o1, o2 = origins[r, 0], origins[r, 1], origins[r, 2]
        d0, d1, d2 = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        t0, t1 = near, far
        for a in range(3):
            o = o0 if a == 0 else (o1 if a == 1 else o2)
            d = d0 if a == 0 else (d1 if a == 1 else d2)
            lo = lo0 if a == 0 else (lo1 if a == 1 else lo2)
            hi = hi0 if a == 0 else (hi1 if a == 1 else hi2)
            if abs(d) < 1e-12:
                if o < lo or o > hi:
                    t1 = -1.0
            else:
                ta, tb = (lo - o) / d, (hi - o) / d
                if ta > tb:
                    ta, tb = tb, ta
                t0 = max(t0, ta)
                t1 = min(t1, tb)
        corner_weight = np.empty(8)
        corner_x = np.empty(8, dtype=np.int64)
        corner_y = np.empty(8, dtype=np.int64)
        corner_z = np.empty(8, dtype=np.int64)
        trans = 1.0
        c0 = c1 = c2 = 0.0
        depth = 0.0
        for c in range(n_classes):
            out_sem[r, c] = 0.0
        t = t0 + 0.5 * step
        while t < t1 and trans > 1e-3:
            g0 = (o0 + t * d0 - lo0) / voxel
            g1 = (o1 + t * d1 - lo1) / voxel
            g2 = (o2 + t * d2 - lo2) / voxel
            b0 = min(max(int(g0 // block), 0), blocks.shape[2] - 1)
            b1 = min(max(int(g1 // block), 0), blocks.shape[1] - 1)
            b2 = min(max(int(g2 // block), 0), blocks.shape[0] - 1)
            if blocks[b2, b1, b0] == 0:
                # jump to where the ray leaves this block
                t_exit = t1
                for a in range(3):
                    d = d0 if a == 0 else (d1 if a == 1 else d2)
                    g = g0 if a == 0 else (g1 if a == 1 else g2)
                    b = b0 if a == 0 else (b1 if a == 1 else b2)
                    if d > 1e-12:
                        t_exit = min(t_exit, t + ((b + 1) * block - g) * voxel / d)
                    elif d < -1e-12:
                        t_exit = min(t_exit, t + (b * block - g) * voxel / d)
                t = max(t_exit, t) + 0.5 * step
                continue
            x0, x1, fx = axis_corners(g0 - 0.5, nx)
            y0, y1, fy = axis_corners(g1 - 0.5, ny)
            z0, z1, fz = axis_corners(g2 - 0.5, nz)
            # the 8 corners once: their sigma-weighted trilinear weights serve sigma, colour and
            # every class
            sigma = 0.0
            for corner in range(8):
                xi = x1 if corner & 1 else x0
                yi = y1 if corner & 2 else y0
                zi = z1 if corner & 4 else z0
                w = (fx if corner & 1 else 1 - fx) * (fy if corner & 2 else 1 - fy) * (fz if corner & 4 else 1 - fz)
                ws = w * density[zi, yi, xi]
                corner_weight[corner] = ws
                corner_x[corner], corner_y[corner], corner_z[corner] = xi, yi, zi
                sigma += ws
            if sigma > 0.0:
                alpha = 1.0 - math.exp(-sigma * step)
                weight = trans * alpha
                scale = weight / (sigma * 255.0)
                a0 = a1 = a2 = 0.0
                for corner in range(8):
                    ws = corner_weight[corner]
                    if ws > 0.0:
                        xi, yi, zi = corner_x[corner], corner_y[corner], corner_z[corner]
                        a0 += ws * rgb[zi, yi, xi, 0]
                        a1 += ws * rgb[zi, yi, xi, 1]
                        a2 += ws * rgb[zi, yi, xi, 2]
                        for c in range(n_classes):
                            out_sem[r, c] += scale * ws * prob[zi, yi, xi, c]
                c0 += scale * a0
                c1 += scale * a1
                c2 += scale * a2
                depth += weight * t
                trans *= 1.0 - alpha
            t += step
        # the sky: latitude-longitude lookup of the ray direction
        norm = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        theta = math.acos(min(1.0, max(-1.0, d2 / norm)))
        phi = math.atan2(d1, d0)
        ei = min(env_h - 1, int(theta / math.pi * env_h))
        ej = min(env_w - 1, int((phi + math.pi) / (2 * math.pi) * env_w))
        out_rgb[r, 0] = c0 + trans * env[ei, ej, 0] / 255.0
        out_rgb[r, 1] = c1 + trans * env[ei, ej, 1] / 255.0
        out_rgb[r, 2] = c2 + trans * env[ei, ej, 2] / 255.0
        for c in range(n_classes):
            out_sem[r, c] += trans * bg_prob[c]
        out_acc[r] = 1.0 - trans
        out_depth[r] = depth / max(1.0 - trans, 1e-10)


# One thread: a simulator usually runs one environment per core, and on a busy machine the parallel
# kernel's threads wait for each other (measured: several times slower than one thread).
march_serial = njit(cache=True, nogil=True)(march.py_func)


class BakedRenderer:
    """Render(P) from baked.zarr: the same call and outputs as SemanticRadianceField.render.
    `threads` 1 marches the rays on the calling thread; more use numba's parallel loop."""

    def __init__(self, path, threads: int = 1):
        self.threads = max(1, int(threads))
        import zarr

        from srfpipe.occupancy.grid import VoxelGrid

        group = zarr.open_group(str(path), mode="r")
        attrs = dict(group.attrs["srfpipe"])
        self.grid = VoxelGrid.from_attrs(attrs["grid"])
        self.block = int(attrs["block"])
        self.density = np.ascontiguousarray(group["density"][...], dtype=np.float32)
        self.rgb = np.ascontiguousarray(group["rgb"][...])
        self.probability = np.ascontiguousarray(group["probability"][...])
        self.blocks = np.ascontiguousarray(group["blocks"][...])
        self.background = np.ascontiguousarray(group["background"][...])
        self.background_probability = np.asarray(attrs["background_probability"], dtype=np.float64)
        self.origin = np.asarray(self.grid.origin, dtype=np.float64)

    def render(self, camera_to_world, intrinsics, width: int, height: int, near: float = 0.0) -> dict:
        from srfpipe.cameras import check_view, pixel_rays
        from srfpipe.memory import check_allocation

        pose, k, width, height = check_view(camera_to_world, intrinsics, width, height)
        c = self.probability.shape[3]
        # origins, directions, the pixel grid, the outputs in float64 and float32
        check_allocation(width * height * (64 + 12 * (5 + c)), "the image size", f"rendering {width} x {height} pixels")
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            origins, dirs = pixel_rays(pose, k, width, height)
        origins, dirs = origins.reshape(-1, 3), dirs.reshape(-1, 3)
        if not np.all(np.isfinite(dirs)):  # the march kernel would read out of its arrays
            raise ValueError(f"intrinsics {k.tolist()} give non-finite ray directions (a focal length too small)")
        n = len(origins)
        rgb, sem = np.empty((n, 3)), np.empty((n, c))
        depth, acc = np.empty(n), np.empty(n)
        arguments = (origins, dirs, self.density, self.rgb, self.probability, self.blocks, self.block, self.origin,
                     self.grid.voxel_size, near, 1e30, self.background, self.background_probability, rgb, sem, depth,
                     acc)
        if self.threads > 1:
            import numba

            # rays through the canopy cost many times those that see the sky: small chunks keep
            # both threads busy (numba's default splits the rays into one block per thread)
            numba.set_num_threads(min(self.threads, numba.config.NUMBA_NUM_THREADS))
            with numba.parallel_chunksize(PARALLEL_CHUNK_RAYS):
                march(*arguments)
        else:
            march_serial(*arguments)
        return {"rgb": np.clip(rgb, 0, 1).reshape(height, width, 3).astype(np.float32),
                "semantic": np.clip(sem, 0, 1).reshape(height, width, c).astype(np.float32),
                "depth": depth.reshape(height, width).astype(np.float32),
                "accumulation": acc.reshape(height, width).astype(np.float32)}
