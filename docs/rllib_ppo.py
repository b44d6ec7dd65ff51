"""Ray RLlib PPO on vgpnav-env with 2 env runners (example; needs ``pip install "ray[rllib]"``).

``vgpnav_env.make_env`` takes one plain-data dict, so ``tune.register_env`` accepts it as it is and
every env runner (a Ray actor, possibly on another machine) builds its own env from the config; the
renderer is created in the process that renders. Dict observations are flattened for RLlib's
default MLP encoder (``FlattenObservations``).

Note: ``ray[rllib]`` pins gymnasium 1.2.x; vgpnav-env works from gymnasium 1.0 on. Install it in
its own virtual environment if your other tools need a newer gymnasium.

Run: ``python docs/rllib_ppo.py --iterations 5`` (model perception on ``home``; see ``--help``).
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from vgpnav_env import make_env

#: The env of every runner: home with the privileged model perception, RL-sized.
CONFIG: dict[str, Any] = {"scene": "home", "perception": "model", "env": {"max_steps": 200}}


def train(
    iterations: int = 5, config: dict[str, Any] | None = None, num_env_runners: int = 2
) -> list[dict[str, Any]]:
    """Run ``iterations`` PPO iterations on ``make_env(config)``; returns each iteration's result."""
    import ray
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.connectors.env_to_module import FlattenObservations
    from ray.tune.registry import register_env

    register_env("vgpnav", make_env)
    algo_config = (
        PPOConfig()
        .environment("vgpnav", env_config=config or CONFIG)
        .env_runners(
            num_env_runners=num_env_runners,
            num_cpus_per_env_runner=0.5,
            rollout_fragment_length=64,
            env_to_module_connector=lambda env, spaces=None, device=None: FlattenObservations(),
        )
        .training(train_batch_size=256, minibatch_size=64, num_epochs=2)
    )
    ray.init(ignore_reinit_error=True, include_dashboard=False, num_cpus=2)
    algo = algo_config.build_algo()
    try:
        return [algo.train() for _ in range(iterations)]
    finally:
        algo.stop()
        ray.shutdown()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--config", type=json.loads, default=CONFIG, help="make_env config as JSON")
    args = parser.parse_args()
    for i, result in enumerate(train(args.iterations, args.config)):
        runners = result["env_runners"]
        print(
            f"iteration {i + 1}: {runners['num_env_steps_sampled_lifetime']} env steps, "
            f"mean return {runners.get('episode_return_mean', float('nan')):.3f}"
        )


if __name__ == "__main__":
    main()
