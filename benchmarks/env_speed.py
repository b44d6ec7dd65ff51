"""Environment speed: env steps per second of ``VGPNav/PointGoal-v0`` (raw and with perception).

Usage: ``python benchmarks/env_speed.py [--scene home] [--size 160x120] [--steps 300]``.
Prints, in one run, wall steps/s and steps per CPU-second (the machine may be shared) of the raw
env, of the privileged ``model`` perception (target >= 300 steps/s; it renders depth only) and of
``VGPNavObservation`` with the ``simulated`` and ``classical`` backbones (classical pixels: target
>= 25 steps/s), the thread pools sized as the CLI sizes them (``configure_threads``).
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np

from vgpnav_env import make_env
from vgpnav_env.perception.backbones.threads import configure_threads
from vgpnav_env.wrappers import VGPNavObservation


def steps_per_second(env: gym.Env, steps: int, seed: int = 0) -> tuple[float, float]:
    """Random-action (wall, CPU) steps per second (resets excluded from the timing)."""
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    env.action_space.seed(seed)
    elapsed, cpu, done_steps = 0.0, 0.0, 0
    while done_steps < steps:
        action = int(rng.choice([1, 1, 2, 3]))  # no stop: keep episodes running
        t, c = time.perf_counter(), time.process_time()
        _, _, terminated, truncated, _ = env.step(action)
        elapsed += time.perf_counter() - t
        cpu += time.process_time() - c
        done_steps += 1
        if terminated or truncated:
            env.reset()
    return done_steps / elapsed, done_steps / cpu


def report(name: str, rates: tuple[float, float], target: str = "") -> None:
    print(f"{name}: {rates[0]:.1f} steps/s wall, {rates[1]:.1f} steps per CPU-second{target}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="home")
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--wrapped-steps", type=int, default=30)
    args = parser.parse_args()
    configure_threads()
    size = tuple(int(v) for v in args.size.split("x"))
    env = gym.make("VGPNav/PointGoal-v0", scene=args.scene, image_size=size)
    env.reset(seed=0)  # build the scene outside the timing
    report(f"raw env {args.scene} {args.size}", steps_per_second(env, args.steps))
    model = make_env({"scene": args.scene, "perception": "model", "env": {"image_size": list(size)}})
    report(
        f"model perception {args.scene} {args.size}", steps_per_second(model, args.steps), " (target >= 300)"
    )
    model.close()
    for backbone in ("simulated", "classical"):
        wrapped = VGPNavObservation(env, backbone=backbone)
        report(
            f"VGPNavObservation({backbone}) {args.scene} {args.size}",
            steps_per_second(wrapped, args.wrapped_steps),
            " (target >= 25)" if backbone == "classical" else "",
        )
    env.close()


if __name__ == "__main__":
    main()
