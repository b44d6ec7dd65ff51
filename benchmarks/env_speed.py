"""Environment speed: env steps per second of ``VGPNav/PointGoal-v0`` (raw and with perception).

Usage: ``python benchmarks/env_speed.py [--scene home] [--size 160x120] [--steps 300]``.
Prints steps/s for the raw env (target >= 100 at 160x120) and, when ``vgpnav_env.wrappers``
exists, for the ``simulated`` and ``classical`` VGP-Nav backbones.
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np

import vgpnav_env  # noqa: F401  (registers the environments)


def steps_per_second(env: gym.Env, steps: int, seed: int = 0) -> float:
    """Random-action steps per second (resets excluded from the timing)."""
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    env.action_space.seed(seed)
    elapsed, done_steps = 0.0, 0
    while done_steps < steps:
        action = int(rng.choice([1, 1, 2, 3]))  # no stop: keep episodes running
        t = time.perf_counter()
        _, _, terminated, truncated, _ = env.step(action)
        elapsed += time.perf_counter() - t
        done_steps += 1
        if terminated or truncated:
            env.reset()
    return done_steps / elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="home")
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--wrapped-steps", type=int, default=30)
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    env = gym.make("VGPNav/PointGoal-v0", scene=args.scene, image_size=size)
    env.reset(seed=0)  # build the scene outside the timing
    print(
        f"raw env {args.scene} {args.size}: {steps_per_second(env, args.steps):.1f} steps/s (target >= 100)"
    )
    try:
        from vgpnav_env.wrappers import VGPNavObservation
    except ImportError:
        print("wrappers not available: skipping the perception backbones")
        return
    for backbone in ("simulated", "classical"):
        wrapped = VGPNavObservation(env, backbone=backbone)
        rate = steps_per_second(wrapped, args.wrapped_steps)
        print(f"VGPNavObservation({backbone}) {args.scene} {args.size}: {rate:.2f} steps/s")
    env.close()


if __name__ == "__main__":
    main()
