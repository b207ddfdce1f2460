"""The robot: a small 5-joint arm with a wrist camera on a mobile lift, written in MJCF for srfpipe.

No arm is copied from elsewhere: it is the smallest arm that reaches a point from a chosen side and
points its camera at it. Sizes are fractions of the reach L (shoulder to tool tip), so one arm
serves a 30 cm plant and a 3 m tree; the package stage picks L from the scene (sim frame, metres)::

    base (mocap body: the lift, placed per target)     box, not checked for contact
     link0  j0 yaw about z       capsule up to the shoulder, height 0.1 L
      link1  j1 shoulder pitch   capsule 0.45 L   (positive pitch lowers the arm: rotation about +y)
       link2  j2 elbow pitch     capsule 0.40 L
        link3 j3 wrist pitch, j4 wrist yaw   capsule 0.15 L, site `tip` at its end, camera `wrist`

Every link is a capsule (`link0..link3`, radius 0.012-0.025 L): these are what the runtime checks
against the occupancy cache. MuJoCo's own contacts are off (contype 0): contact with the scene is
the cache's. Joints are driven by position servos with gravity compensation. The wrist camera looks
along link3's +x (MuJoCo cameras look down their -z, +y up).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

JOINTS = ("j0_yaw", "j1_shoulder", "j2_elbow", "j3_wrist_pitch", "j4_wrist_yaw")
LINKS = ("link0", "link1", "link2", "link3")


@dataclass(frozen=True)
class ArmSpec:
    """Arm geometry in sim metres, all derived from the reach (shoulder to tool tip)."""

    reach: float
    wrist_fovy_deg: float = 70.0

    @property
    def shoulder_height(self) -> float:
        return 0.1 * self.reach

    @property
    def lengths(self) -> tuple[float, float, float]:
        return 0.45 * self.reach, 0.40 * self.reach, 0.15 * self.reach

    @property
    def radii(self) -> tuple[float, float, float, float]:
        return 0.025 * self.reach, 0.02 * self.reach, 0.016 * self.reach, 0.012 * self.reach

    @property
    def max_radius(self) -> float:
        return max(self.radii)

    # joint limits (radians), home pose: folded up and back, camera looking forward
    ranges = ((-math.pi, math.pi), (-1.75, 1.75), (-2.6, 2.6), (-2.1, 2.1), (-1.6, 1.6))
    home = (0.0, -0.9, 1.9, -1.0, 0.0)

    def describe(self) -> dict:
        return {
            "source": "written for srfpipe (srfpipe/sim/arm.py): 5 revolute joints on a mobile lift",
            "reach": self.reach, "shoulder_height": self.shoulder_height, "link_lengths": list(self.lengths),
            "link_radii": list(self.radii), "joints": list(JOINTS), "joint_ranges": [list(r) for r in self.ranges],
            "home": list(self.home), "links": list(LINKS), "wrist_fovy_deg": self.wrist_fovy_deg,
            "tip_site": "tip", "wrist_camera": "wrist", "base_body": "base",
            **{k: v for k, v in asdict(self).items() if k not in ("reach", "wrist_fovy_deg")},
        }


def _f(values) -> str:
    return " ".join(f"{float(v):.6g}" for v in np.ravel(values))


def arm_mjcf(spec: ArmSpec, base_pos, base_yaw: float) -> str:
    """The arm's bodies (an MJCF <body> element, text) with the base at `base_pos`, facing `base_yaw`."""
    l1, l2, l3 = spec.lengths
    r0, r1, r2, r3 = spec.radii
    h0 = spec.shoulder_height
    L = spec.reach
    quat = [math.cos(base_yaw / 2), 0.0, 0.0, math.sin(base_yaw / 2)]
    rng = spec.ranges
    capsule = 'contype="0" conaffinity="0" group="1" rgba="{rgba}"'
    grey, orange = capsule.format(rgba="0.75 0.75 0.78 1"), capsule.format(rgba="0.95 0.55 0.15 1")
    return f"""
    <body name="base" mocap="true" pos="{_f(base_pos)}" quat="{_f(quat)}">
      <geom name="platform" type="box" size="{_f([0.12 * L, 0.12 * L, 0.02 * L])}" pos="0 0 {-0.02 * L:.6g}"
            contype="0" conaffinity="0" group="1" rgba="0.2 0.2 0.25 1" mass="0"/>
      <body name="link0" gravcomp="1">
        <joint name="j0_yaw" type="hinge" axis="0 0 1" range="{_f(rng[0])}" damping="{2.0 * L:.6g}" armature="0.01"/>
        <geom name="link0" type="capsule" fromto="0 0 0 0 0 {h0:.6g}" size="{r0:.6g}" {grey}/>
        <body name="link1" pos="0 0 {h0:.6g}" gravcomp="1">
          <joint name="j1_shoulder" type="hinge" axis="0 1 0" range="{_f(rng[1])}" damping="{2.0 * L:.6g}" armature="0.01"/>
          <geom name="link1" type="capsule" fromto="0 0 0 {l1:.6g} 0 0" size="{r1:.6g}" {orange}/>
          <body name="link2" pos="{l1:.6g} 0 0" gravcomp="1">
            <joint name="j2_elbow" type="hinge" axis="0 1 0" range="{_f(rng[2])}" damping="{1.0 * L:.6g}" armature="0.01"/>
            <geom name="link2" type="capsule" fromto="0 0 0 {l2:.6g} 0 0" size="{r2:.6g}" {grey}/>
            <body name="link3" pos="{l2:.6g} 0 0" gravcomp="1">
              <joint name="j3_wrist_pitch" type="hinge" axis="0 1 0" range="{_f(rng[3])}" damping="{0.5 * L:.6g}" armature="0.005"/>
              <joint name="j4_wrist_yaw" type="hinge" axis="0 0 1" range="{_f(rng[4])}" damping="{0.5 * L:.6g}" armature="0.005"/>
              <geom name="link3" type="capsule" fromto="0 0 0 {l3:.6g} 0 0" size="{r3:.6g}" {orange}/>
              <site name="tip" pos="{l3:.6g} 0 0" size="{0.6 * r3:.6g}" rgba="1 0 0 1"/>
              <camera name="wrist" pos="{0.5 * l3:.6g} 0 {1.2 * r3:.6g}" xyaxes="0 -1 0 0 0 1" fovy="{spec.wrist_fovy_deg:.6g}"/>
            </body>
          </body>
        </body>
      </body>
    </body>"""


def actuators_mjcf(spec: ArmSpec) -> str:
    """Position servos on every joint (targets within the joint ranges)."""
    L = spec.reach
    gains = (60.0, 60.0, 40.0, 15.0, 15.0)
    lines = []
    for name, (lo, hi), kp in zip(JOINTS, spec.ranges, gains):
        kp = kp * L * L  # link inertia grows with L^3 x density, torques with L: keep the bandwidth
        lines.append(f'<position name="{name}" joint="{name}" kp="{kp:.6g}" kv="{0.15 * kp:.6g}" '
                     f'ctrlrange="{lo:.6g} {hi:.6g}"/>')
    return "\n    ".join(lines)
