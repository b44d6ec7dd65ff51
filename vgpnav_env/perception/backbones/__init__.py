"""Feed-forward reconstruction backbones (DESIGN.md, Perception step 3) and their registry.

:func:`make_backbone` is the one way to get a backbone: ``make_backbone(name, database=db,
seed=s, **options)`` builds ``classical`` (default, pixels only; with a ``database`` it reads the
database's stored features, after checking they were extracted with its settings, and matches
with XFeat + LighterGlue where the database's own pairs show RootSIFT failing:
:mod:`~vgpnav_env.perception.feature_choice`),
``simulated`` (PRIVILEGED ground truth + noise; ``seed`` seeds its noise) or ``learned`` (needs
``model`` and a local ``weights_path``; nothing is downloaded). :data:`BACKBONES` lists the names
(command-line choices read it). A backbone is reseeded per episode with :meth:`Backbone.reseed`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from vgpnav_env.perception.backbones.base import Backbone, BackboneOutput, Privileged
from vgpnav_env.perception.backbones.classical import ClassicalBackbone, ClassicalConfig, FeatureCache
from vgpnav_env.perception.backbones.simulated import SimulatedBackbone, SimulatedConfig

if TYPE_CHECKING:
    from vgpnav_env.perception.database import Database

__all__ = [
    "BACKBONES",
    "Backbone",
    "BackboneOutput",
    "ClassicalBackbone",
    "ClassicalConfig",
    "FeatureCache",
    "Privileged",
    "SimulatedBackbone",
    "SimulatedConfig",
    "make_backbone",
]

Seed = int | np.random.Generator | None


def _one_config(config: Any, knobs: dict[str, Any], kind: str) -> None:
    if config is not None and knobs:
        raise ValueError(f"give either `config` or individual {kind} fields, not both")


def _classical(
    database: Database | None, seed: Seed, config: ClassicalConfig | None = None, **knobs: Any
) -> Backbone:
    _one_config(config, knobs, "ClassicalConfig")
    config = config or ClassicalConfig(**knobs)
    if database is None:
        return ClassicalBackbone(config)
    if config.checks_scene:
        from vgpnav_env.perception.feature_choice import choose_features

        if choose_features(database, config).features == "xfeat":
            config = config.switch_config()
    fallback = database.features_for(config.fallback_config(), every=False) if config.uses_fallback else None
    return ClassicalBackbone(config, database.features_for(config), fallback)


def _simulated(
    database: Database | None, seed: Seed, config: SimulatedConfig | None = None, **knobs: Any
) -> Backbone:
    _one_config(config, knobs, "SimulatedConfig")
    return SimulatedBackbone(config or SimulatedConfig(**knobs), seed)


def _learned(database: Database | None, seed: Seed, **options: Any) -> Backbone:
    missing = [name for name in ("model", "weights_path") if options.get(name) is None]
    if missing:
        raise ValueError(
            f"the learned backbone needs {' and '.join(missing)}: model= a torch module, a factory or "
            "'package.module:factory', weights_path= a local checkpoint (nothing is downloaded)"
        )
    # Imported lazily: torch loads only when a learned backbone is asked for.
    from vgpnav_env.perception.backbones.learned import LearnedBackbone

    return LearnedBackbone(**options)


#: Backbone name -> builder ``(database, seed, **options) -> Backbone`` (use :func:`make_backbone`).
BACKBONES: dict[str, Callable[..., Backbone]] = {
    "classical": _classical,
    "simulated": _simulated,
    "learned": _learned,
}


def make_backbone(
    name: str = "classical", *, database: Database | None = None, seed: Seed = None, **options: Any
) -> Backbone:
    """The backbone ``name`` for ``database`` (see the module docstring).

    ``database``: the database it will run against (the classical backbone then reuses its stored
    reference features; a ValueError if they were extracted with other settings). ``seed``: the
    random stream of a random backbone (deterministic ones ignore it). ``options``: the backbone's
    config fields, its ``config`` object, or its constructor arguments (``learned``).
    """
    if name not in BACKBONES:
        raise ValueError(f"unknown backbone {name!r}; choose one of {sorted(BACKBONES)}")
    return BACKBONES[name](database, seed, **options)
