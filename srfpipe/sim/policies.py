"""Policies for `srfpipe/AppleReach-v0`: a scripted baseline and a random one to compare against.

ScriptedPolicy (privileged: it reads the simulator's state, not the pixels) moves the tool tip along
the station's straight approach corridor with damped-least-squares Jacobian steps, in three tasks:

1. the tip follows a carrot on the segment from where it is to the fruit's surface (a look-ahead of
   `lookahead` x reach along the approach line, pulled back onto the line), and never leaves the
   corridor that made the target reachable;
2. in the tip task's null space, every link whose clearance to the avoid classes (the occupancy
   cache's signed distance minus the link radius) is below `margin` x reach is pushed along the
   distance gradient, harder the closer it is; when a link is within a quarter of the margin that
   push is applied before the tip task (safety first);
3. also in the null space, the wrist link turns to point along the approach (the camera sees the fruit).

RandomPolicy samples the action space with its own seeded generator.
"""

from __future__ import annotations

import numpy as np


def damped_pinv(jac: np.ndarray, damping: float) -> np.ndarray:
    """J^T (J J^T + lambda^2 I)^-1: the damped least-squares inverse (finite near singularities)."""
    jjt = jac @ jac.T
    return jac.T @ np.linalg.inv(jjt + damping ** 2 * np.eye(jjt.shape[0]))


class RandomPolicy:
    def __init__(self, action_space, seed: int | None = None):
        self.action_space = action_space
        self.rng = np.random.default_rng(seed)

    def __call__(self, observation=None, info=None) -> np.ndarray:
        low, high = self.action_space.low, self.action_space.high
        return self.rng.uniform(low, high).astype(self.action_space.dtype)


class ScriptedPolicy:
    def __init__(self, env, lookahead: float = 0.08, margin: float = 0.05, gain: float = 0.7):
        self.env = env.unwrapped
        self.sim = self.env.sim
        self.reach = self.env.reach
        self.lookahead = lookahead * self.reach
        self.margin = margin * self.reach
        self.gain = gain

    def _goal(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        target = self.env.target_info
        centre = np.asarray(target["centroid_sim"])
        approach = np.asarray(self.sim.station["approach"]) if self.sim.station else np.array([1.0, 0.0, 0.0])
        approach /= np.linalg.norm(approach)
        surface = centre - approach * target["radius_sim"] * 0.6  # a little into the fruit: success is near it
        return centre, surface, approach

    def __call__(self, observation=None, info=None) -> np.ndarray:
        sim = self.sim
        tip = sim.tip()
        centre, surface, approach = self._goal()
        # carrot on the approach line: project the tip, step ahead, stop at the surface
        along = float(np.dot(tip - surface, approach))  # negative before the surface
        carrot = surface + min(0.0, along + self.lookahead) * approach
        error = carrot - tip
        error_norm = np.linalg.norm(error)
        if error_norm > self.lookahead:
            error *= self.lookahead / error_norm
        jac = sim.tip_jacobian()
        pinv = damped_pinv(jac, 0.05 * self.reach)
        n = jac.shape[1]
        null = np.eye(n) - pinv @ jac
        dq_task = pinv @ error

        # clearance: push links away from the avoid classes
        contact = sim.contact()
        dq_safe = np.zeros(n)
        urgent = False
        for link, clearance in enumerate(contact.clearance):
            if clearance >= self.margin or not np.isfinite(clearance):
                continue
            grad = contact.link_gradients[link]
            g = np.linalg.norm(grad)
            if g < 1e-9:
                continue
            jl = self._closest_point_jacobian(link)
            push = (self.margin - clearance) * grad / g
            dq_safe += damped_pinv(jl, 0.05 * self.reach) @ push
            urgent |= clearance < 0.25 * self.margin

        # the wrist points along the approach (camera toward the fruit)
        wrist_x = sim.data.xmat[sim.model.geom_bodyid[sim.link_geoms[-1]]].reshape(3, 3)[:, 0]
        rot_error = np.cross(wrist_x, approach)
        jr = self._wrist_rotation_jacobian()
        dq_orient = damped_pinv(jr, 0.1) @ (0.5 * rot_error)

        if urgent:
            dq = dq_safe + 0.3 * dq_task
        else:
            dq = dq_task + null @ (dq_safe + 0.5 * dq_orient)
        target_q = sim.qpos + self.gain * dq
        action = (target_q - sim.data.ctrl) / self.env.max_delta
        return np.clip(action, -1.0, 1.0).astype(np.float32)

    def _closest_point_jacobian(self, link: int) -> np.ndarray:
        starts, ends = self.sim.link_segments()
        # the deepest point of this link: sample its axis like the contact query does
        n = int(self.sim.link_samples[link])
        t = np.linspace(0.0, 1.0, n)
        points = starts[link] + t[:, None] * (ends[link] - starts[link])
        d, _ = self.sim.fields.query(points)
        point = points[int(np.argmin(d))]
        return self.sim.point_jacobian(point, link)

    def _wrist_rotation_jacobian(self) -> np.ndarray:
        import mujoco

        sim = self.sim
        jacr = np.zeros((3, sim.model.nv))
        body = sim.model.geom_bodyid[sim.link_geoms[-1]]
        mujoco.mj_jacBody(sim.model, sim.data, None, jacr, body)
        return jacr[:, sim.dof_adr]
