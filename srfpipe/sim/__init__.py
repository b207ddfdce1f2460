"""The simulator: the paper's application loop (Sec. 3, Fig. 2) on a packaged scene.

* `srfpipe.sim.package` (`srfpipe package`): results/{scene}/sim/ (manifest, fruit targets, meshes,
  MJCF, the baked field) from occupancy.zarr and srf.zarr.
* `srfpipe.sim.runtime.Simulator`: MuJoCo steps the arm, the SRF renders the wrist camera, the
  occupancy cache gives contact (penetration, distance gradient).
* `srfpipe.sim.env`: the Gymnasium environment `srfpipe/AppleReach-v0` (registered on import of
  this package); `srfpipe.sim.policies`: scripted and random policies.
* `srfpipe.sim.rollout` (`srfpipe sim`): episodes from the command line, written as a GIF.
"""

from __future__ import annotations

import os

# MuJoCo picks its OpenGL back end when it is first imported: headless EGL unless the user chose
# (Debian packages libegl1, libegl-mesa0, libgl1-mesa-dri; MUJOCO_GL=osmesa needs libosmesa6).
os.environ.setdefault("MUJOCO_GL", "egl")


def _register() -> None:
    try:
        from srfpipe.sim.env import register_envs
    except ModuleNotFoundError:  # gymnasium is in the `sim` extra
        return
    register_envs()


_register()
