"""`srfpipe/AppleReach-v0`: reach a fruit with the arm's tool tip without touching an avoid class.

    import gymnasium as gym, srfpipe.sim                     # importing srfpipe.sim registers it
    env = gym.make("srfpipe/AppleReach-v0", package="results/orchard/sim")
    # or, without the import: gym.make("srfpipe.sim:srfpipe/AppleReach-v0", package=...)

* Observation (Dict): `rgb` (H, W, 3) uint8 and `semantic` (H, W, C) uint8 (round(255 p) per class)
  rendered by the SRF from the wrist camera; `joints` (2 n,) float32: joint angles (within their
  ranges) and velocities (clipped to +-20 rad/s).
* Action: (n,) in [-1, 1], a change of each joint's servo target of at most `max_delta` radians.
* Reward: -distance(tool tip, target's surface) / reach every step, +`success_bonus` on success,
  -`collision_penalty` on contact. It rises as the tip approaches the target.
* Terminated: on contact with an avoid class (a link capsule inside it, by the occupancy cache), or
  on success (the tip within `success_margin` fruit radii of the fruit's surface). Truncated by
  the TimeLimit wrapper after `max_episode_steps` (150). A step after termination raises
  RuntimeError (it would pay the success bonus again): reset first.
* Reset: the target is drawn with the env's `np_random` from the reachable targets (or set with
  `options={"target": i}`); the arm starts at home at that target's station. The same seed gives
  the same rollout: MuJoCo and the SRF's eval-mode render are deterministic on the CPU.
* `info`: distance, success, collision, penetration, clearance per link, the distance gradient,
  target index, tip and target positions (sim metres).
"""

from __future__ import annotations

import numpy as np

try:
    import gymnasium as gym
    from gymnasium import spaces
except ModuleNotFoundError as exc:  # the `sim` extra
    raise ModuleNotFoundError("srfpipe.sim.env needs gymnasium: pip install -e '.[sim]'") from exc

from srfpipe.sim.runtime import Simulator

ENV_ID = "srfpipe/AppleReach-v0"
MAX_EPISODE_STEPS = 150
MAX_JOINT_SPEED = 20.0  # rad/s: the joints observation is clipped to it (the servos stay far below)


class AppleReachEnv(gym.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 25}

    def __init__(self, package, render_mode: str | None = None, wrist_size: int = 64, max_delta: float = 0.06,
                 success_margin: float | None = None, success_bonus: float = 10.0, collision_penalty: float = 10.0,
                 reachable_only: bool = True, device: str = "cpu", view_size: tuple[int, int] = (240, 320),
                 observe_wrist: bool = True):
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        if int(wrist_size) < 1:
            raise ValueError(f"wrist_size must be at least 1 pixel, got {wrist_size}")
        if not (np.isfinite(max_delta) and max_delta > 0):
            raise ValueError(f"max_delta must be a positive number of radians, got {max_delta}")
        self.sim = Simulator(package, device=device, wrist_size=(wrist_size, wrist_size))
        task = self.sim.manifest.get("task")
        if not task:
            raise ValueError(f"{package}: the package has no targets ({self.sim.manifest.get('note')})")
        pool = task["reachable_targets"] if reachable_only else list(range(len(self.sim.targets)))
        if not pool:
            raise ValueError(f"{package}: no reachable target (see targets.json stations)")
        self.pool = list(pool)
        self.render_mode = render_mode
        self.observe_wrist = bool(observe_wrist)  # False: no wrist render, rgb/semantic zeros (privileged policies)
        self.view_size = view_size
        self.max_delta = float(max_delta)
        self.success_margin = float(task["success_margin"] if success_margin is None else success_margin)
        self.success_bonus, self.collision_penalty = float(success_bonus), float(collision_penalty)
        self.reach = float(self.sim.arm["reach"])
        n = len(self.sim.joint_ids)
        c = len(self.sim.classes)
        self.observation_space = spaces.Dict({
            "rgb": spaces.Box(0, 255, (wrist_size, wrist_size, 3), np.uint8),
            "semantic": spaces.Box(0, 255, (wrist_size, wrist_size, c), np.uint8),
            "joints": spaces.Box(np.concatenate([self.sim.ctrl_range[:, 0], np.full(n, -MAX_JOINT_SPEED)]).astype(np.float32),
                                 np.concatenate([self.sim.ctrl_range[:, 1], np.full(n, MAX_JOINT_SPEED)]).astype(np.float32),
                                 (2 * n,), np.float32),
        })
        self.action_space = spaces.Box(-1.0, 1.0, (n,), np.float32)
        self.target = self.pool[0]
        self._renderer = None
        self._last_view = None
        self._terminated = False  # the episode ended (success or contact): step needs a reset first

    # ------------------------------------------------------------------ helpers

    @property
    def last_view(self) -> dict | None:
        """The wrist render behind the latest observation (Simulator.render_wrist: rgb, semantic, ...),
        None before the first or when the wrist is not observed."""
        return self._last_view

    @property
    def target_info(self) -> dict:
        return self.sim.targets[self.target]

    def target_distance(self, tip=None) -> float:
        """Distance from the tool tip (or `tip`) to the target's surface, sim metres (0 inside it)."""
        t = self.target_info
        tip = self.sim.tip() if tip is None else np.asarray(tip)
        return max(0.0, float(np.linalg.norm(tip - np.asarray(t["centroid_sim"]))) - t["radius_sim"])

    def reward_for(self, distance: float, success: bool, collision: bool) -> float:
        return -distance / self.reach + self.success_bonus * success - self.collision_penalty * collision

    def _observation(self) -> dict:
        if not self.observe_wrist:
            space = self.observation_space
            return {"rgb": np.zeros(space["rgb"].shape, np.uint8), "semantic": np.zeros(space["semantic"].shape, np.uint8),
                    "joints": self._joints()}
        view = self.sim.render_wrist()
        self._last_view = view
        sem = view["semantic"]
        return {
            "rgb": np.clip(np.round(view["rgb"] * 255), 0, 255).astype(np.uint8),
            "semantic": np.clip(np.round(sem * 255), 0, 255).astype(np.uint8).reshape(self.observation_space["semantic"].shape),
            "joints": self._joints(),
        }

    def _joints(self) -> np.ndarray:
        return np.concatenate([np.clip(self.sim.qpos, self.sim.ctrl_range[:, 0], self.sim.ctrl_range[:, 1]),
                               np.clip(self.sim.qvel, -MAX_JOINT_SPEED, MAX_JOINT_SPEED)]).astype(np.float32)

    def _info(self, contact, distance: float, success: bool) -> dict:
        return {
            "distance": distance, "success": success, "collision": contact.in_contact,
            "penetration": contact.penetration, "clearance": contact.clearance.copy(),
            "gradient": contact.gradient.copy(), "target": self.target,
            "tip": self.sim.tip(), "target_position": np.asarray(self.target_info["centroid_sim"]),
        }

    # ------------------------------------------------------------------ gymnasium API

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = options or {}
        if options.get("target") is not None:
            target = int(options["target"])
            if not 0 <= target < len(self.sim.targets):
                raise ValueError(f"target {target} out of range (the package has {len(self.sim.targets)})")
            self.target = target
        else:
            self.target = int(self.pool[self.np_random.integers(len(self.pool))])
        self.sim.reset(target=self.target)
        self._terminated = False
        contact = self.sim.contact()
        distance = self.target_distance()
        return self._observation(), self._info(contact, distance, False)

    def step(self, action):
        if self._terminated:
            raise RuntimeError("step after the episode terminated (success or contact): call reset() first")
        action = np.asarray(action, dtype=np.float64)
        if action.size != self.action_space.shape[0]:
            raise ValueError(f"action must hold one value per joint, shape {self.action_space.shape}, "
                             f"got shape {action.shape}")
        if np.isnan(action).any():
            raise ValueError(f"action must not be NaN, got {action.tolist()}")
        action = np.clip(action.reshape(self.action_space.shape), -1.0, 1.0)
        contact = self.sim.step(self.sim.data.ctrl + action * self.max_delta)
        distance = self.target_distance()
        success = bool(distance <= self.success_margin * self.target_info["radius_sim"]) and not contact.in_contact
        reward = self.reward_for(distance, success, contact.in_contact)
        terminated = bool(success or contact.in_contact)
        self._terminated = terminated
        return self._observation(), float(reward), terminated, False, self._info(contact, distance, success)

    def render(self):
        """rgb_array: the third-person view (MuJoCo's offscreen renderer, headless through EGL)."""
        if self.render_mode != "rgb_array":
            return None
        return self.third_person()

    def third_person(self) -> np.ndarray:
        """The arm and its target from the side of the approach, a little above."""
        from srfpipe.sim.runtime import ThirdPersonCamera

        if self._renderer is None:
            self._renderer = ThirdPersonCamera(self.sim, *self.view_size)
        target = np.asarray(self.target_info["centroid_sim"])
        base = np.asarray((self.sim.station or {}).get("base", target))
        approach = target - base
        azimuth = float(np.degrees(np.arctan2(approach[1], approach[0]))) + 70.0
        return self._renderer.render(0.5 * (self.sim.tip() + target), 1.6 * self.reach, azimuth)

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def register_envs() -> None:
    if ENV_ID not in gym.registry:
        gym.register(id=ENV_ID, entry_point="srfpipe.sim.env:AppleReachEnv", max_episode_steps=MAX_EPISODE_STEPS)
