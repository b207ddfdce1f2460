"""Run apple-reaching episodes in a simulator package and write them as a GIF.

    srfpipe sim --package results/orchard/sim --policy scripted --episodes 3 --out rollout.gif

Each frame shows the wrist camera's RGB and semantic map (rendered by the SRF, class colours as in
the eval renders) beside a third-person view from MuJoCo's offscreen renderer, headless through EGL
(Debian: libegl1, libegl-mesa0, libgl1-mesa-dri; set MUJOCO_GL=osmesa with libosmesa6 instead).
A package without targets (a scene without a reach class) runs the arm with random joint targets,
for contact and views only. Prints one JSON line per episode (target, steps, return, success,
collision) and a summary.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def semantic_view(rgb: np.ndarray, semantic: np.ndarray, classes: list[str], threshold: float = 0.5) -> np.ndarray:
    """The wrist RGB blended with the colour of each pixel's most probable class above threshold."""
    from srfpipe.evaluate import class_colours, semantic_blend

    if semantic.shape[-1] == 0:
        return np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8)
    best = semantic.argmax(axis=-1)
    label = np.where(semantic.max(axis=-1) >= threshold, best + 1, 0)
    return semantic_blend(rgb, label, class_colours(classes))


def compose(wrist_rgb: np.ndarray, wrist_sem: np.ndarray, third: np.ndarray, caption: str) -> np.ndarray:
    """wrist RGB | semantic | third person, the wrist views scaled (nearest) to the third's height."""
    import cv2

    h = third.shape[0]
    panels = [cv2.resize(np.ascontiguousarray(v), (h, h), interpolation=cv2.INTER_NEAREST) for v in (wrist_rgb, wrist_sem)]
    frame = np.concatenate(panels + [third], axis=1)
    cv2.putText(frame, caption, (6, h - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return frame


def write_gif(frames: list[np.ndarray], path: Path, fps: float) -> None:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.partial")
    images = [Image.fromarray(f) for f in frames]
    images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
    tmp.replace(path)


def run_episodes(package, policy: str, episodes: int, max_steps: int, seed: int, wrist_size: int = 64,
                 renderer: str = "baked", view_size=(240, 320), frame_every: int = 1, frames: list | None = None):
    """Episodes with `policy` ('scripted' | 'random'); returns per-episode dicts; appends frames when given."""
    import gymnasium as gym

    import srfpipe.sim  # noqa: F401  (registers the env)
    from srfpipe.sim.policies import RandomPolicy, ScriptedPolicy

    env = gym.make("srfpipe/AppleReach-v0", package=str(package), wrist_size=wrist_size, view_size=view_size,
                   render_mode="rgb_array" if frames is not None else None, max_episode_steps=max_steps)
    env.unwrapped.sim.renderer = renderer
    classes = env.unwrapped.sim.classes
    results = []
    for episode in range(episodes):
        obs, info = env.reset(seed=seed + episode)
        actor = ScriptedPolicy(env) if policy == "scripted" else RandomPolicy(env.action_space, seed=seed + episode)
        total, steps, terminated, truncated = 0.0, 0, False, False
        while not (terminated or truncated):
            obs, reward, terminated, truncated, info = env.step(actor(obs, info))
            total += reward
            steps += 1
            if frames is not None and (steps % frame_every == 0 or terminated or truncated):
                view = env.unwrapped.last_view
                status = "SUCCESS" if info["success"] else ("CONTACT" if info["collision"] else "")
                caption = (f"{policy} ep {episode} step {steps} d={info['distance']:.3f} m "
                           f"clear={float(np.min(info['clearance'])):.3f} m {status}")
                frames.append(compose(obs["rgb"], semantic_view(view["rgb"], view["semantic"], classes),
                                      env.render(), caption))
        results.append({"episode": episode, "target": int(info["target"]), "steps": steps, "return": total,
                        "success": bool(info["success"]), "collision": bool(info["collision"]),
                        "final_distance": float(info["distance"])})
    env.close()
    return results


def run_free(package, episodes: int, max_steps: int, seed: int, wrist_size: int, renderer: str, view_size,
             frames: list | None):
    """A package without targets: random joint targets, contact reported, no task."""
    from srfpipe.sim.runtime import Simulator, ThirdPersonCamera

    sim = Simulator(package, wrist_size=(wrist_size, wrist_size), renderer=renderer)
    camera = ThirdPersonCamera(sim, *view_size) if frames is not None else None
    results = []
    for episode in range(episodes):
        rng = np.random.default_rng(seed + episode)
        sim.reset()
        contacts = 0
        for step in range(max_steps):
            contact = sim.step(sim.data.ctrl + rng.uniform(-0.06, 0.06, size=sim.data.ctrl.shape))
            contacts += contact.in_contact
            if frames is not None:
                view = sim.render_wrist()
                rgb = np.clip(np.round(view["rgb"] * 255), 0, 255).astype(np.uint8)
                third = camera.render(sim.tip(), 1.6 * sim.arm["reach"], 60.0)
                frames.append(compose(rgb, semantic_view(view["rgb"], view["semantic"], sim.classes), third,
                                      f"free ep {episode} step {step + 1} clear={float(contact.clearance.min()):.3f} m"))
        results.append({"episode": episode, "steps": max_steps, "contact_steps": int(contacts)})
    if camera is not None:
        camera.close()
    return results


def add_arguments(parser) -> None:
    parser.add_argument("--package", required=True, metavar="DIR", help="simulator package (results/{scene}/sim)")
    parser.add_argument("--policy", choices=["scripted", "random"], default="scripted", help="who moves the arm")
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--max-steps", type=int, default=150, help="steps per episode (0.04 s each)")
    parser.add_argument("--seed", type=int, default=0, help="episode i is reset with seed + i")
    parser.add_argument("--wrist-size", type=int, default=64, help="wrist camera width and height (pixels)")
    parser.add_argument("--renderer", choices=["baked", "field"], default="baked",
                        help="wrist views from the baked field (fast) or the network (exact, slow on a CPU)")
    parser.add_argument("--frame-every", type=int, default=1, help="keep every n-th step in the GIF")
    parser.add_argument("--fps", type=float, default=12.5)
    parser.add_argument("--out", metavar="GIF", help="write the rollout here (none: numbers only)")


def check_arguments(args) -> None:
    """Refuse, naming the flag, what would run nothing (0 episodes: a NaN success rate, no GIF),
    run without end (a negative --max-steps), or fail only after the episodes (a negative --seed,
    --fps 0)."""
    for flag, value, least in (("--episodes", args.episodes, 1), ("--max-steps", args.max_steps, 1),
                               ("--seed", args.seed, 0), ("--wrist-size", args.wrist_size, 1)):
        if value < least:
            raise ValueError(f"{flag} must be at least {least}, got {value}")
    if not (np.isfinite(args.fps) and args.fps > 0):
        raise ValueError(f"--fps must be a positive number, got {args.fps}")


def run(args) -> int:
    check_arguments(args)
    package = Path(args.package)
    if not (package / "scene.json").exists():
        raise FileNotFoundError(f"{package}: not a simulator package (run `srfpipe package`)")
    frames: list | None = [] if args.out else None
    manifest = json.loads((package / "scene.json").read_text())
    view_size = (240, 320)
    if manifest.get("task"):
        results = run_episodes(package, args.policy, args.episodes, args.max_steps, args.seed, args.wrist_size,
                               args.renderer, view_size, max(1, args.frame_every), frames)
    else:
        log.warning("%s: %s; running the arm with random joint targets", package, manifest.get("note"))
        results = run_free(package, args.episodes, args.max_steps, args.seed, args.wrist_size, args.renderer,
                           view_size, frames)
    for result in results:
        print(json.dumps(result))
    if manifest.get("task"):
        print(json.dumps({"policy": args.policy, "episodes": len(results),
                          "success_rate": float(np.mean([r["success"] for r in results])),
                          "collision_rate": float(np.mean([r["collision"] for r in results]))}))
    if frames:
        write_gif(frames, Path(args.out), args.fps)
        print(f"wrote {args.out} ({len(frames)} frames)")
    return 0
