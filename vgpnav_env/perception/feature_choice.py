"""Which local features suit a scene, judged on its database's own posed image pairs.

RootSIFT matches the textured scenes this project generates well and fails on plain painted walls
and untextured furniture, where XFeat + LighterGlue gets more pairs right. The database's images
come with their metric poses, so each scene can be tested before a query arrives:
:func:`choose_features` takes ``SAMPLE_FRAMES`` evenly spaced database frames, pairs each with its
:func:`~vgpnav_env.perception.database.prior_neighbours` (the overlapping views the prior map is
reconstructed from) and counts the pairs whose two-view pose is right (rotation within
``RIGHT_DEG[0]``, translation direction within ``RIGHT_DEG[1]`` degrees of the known relative
pose). When RootSIFT gets fewer than ``ClassicalConfig.switch_share`` of them right and
XFeat + LighterGlue gets significantly more of the same pairs right (a one-sided sign test on the
pairs only one of them gets right, at ``SIGNIFICANCE``: the switch costs CPU, so a gain within the
sample's noise does not pay), the classical backbone matches every pair with XFeat + LighterGlue
(:meth:`~vgpnav_env.perception.backbones.ClassicalConfig.fallback_config`). Only database images
and poses are read; the result is cached beside the database's index, keyed by its fingerprint and
the feature settings.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray
from scipy.stats import binomtest

from vgpnav_env.atomic import atomic_write
from vgpnav_env.geometry import invert_pose, rotation_angle
from vgpnav_env.perception.backbones.classical import (
    ClassicalBackbone,
    ClassicalConfig,
    backbone_feature_settings,
)
from vgpnav_env.runs import run_fingerprint

if TYPE_CHECKING:
    from vgpnav_env.perception.database import Database, DatabaseConfig

logger = logging.getLogger(__name__)

#: Database frames tested (evenly spaced), each with its prior neighbours (up to 5).
SAMPLE_FRAMES = 30
#: A pair is right within this rotation and translation direction error (degrees).
RIGHT_DEG = (5.0, 10.0)
#: The sign test's level (the conventional one, not fitted): XFeat must win the pairs the two
#: matchers disagree on by more than chance would at this level.
SIGNIFICANCE = 0.05
_VERSION = 2


@dataclass(frozen=True)
class FeatureChoice:
    """The features the backbone uses on a database (``"rootsift"`` or ``"xfeat"``), with the
    shares of its tested pairs each got right and the sign test's p-value (``xfeat`` and ``p``
    None when RootSIFT passed the test)."""

    features: str
    rootsift: float
    xfeat: float | None
    n_pairs: int
    p: float | None = None

    def describe(self) -> str:
        """One line for reports, e.g. ``xfeat (database pairs right: RootSIFT 0.06, XFeat 0.18 of
        147, p 0.0001)``."""
        shares = f"RootSIFT {self.rootsift:.2f}"
        if self.xfeat is not None:
            shares += f", XFeat {self.xfeat:.2f}"
        tested = "" if self.p is None else f", p {self.p:.2g}"
        return f"{self.features} (database pairs right: {shares} of {self.n_pairs}{tested})"


def pair_outcomes(db: Database, config: ClassicalConfig, progress: bool = False) -> NDArray[np.bool_]:
    """Whether the backbone with ``config`` gets each tested database pair right (module
    docstring), in a fixed pair order (empty when the database has no overlapping views)."""
    from vgpnav_env.perception.database import prior_neighbours

    config = replace(config, fallback_pairs=0)
    backbone = ClassicalBackbone(config, db.features_for(config, progress=progress, every=False))
    right = []
    for j in np.unique(np.linspace(0, len(db) - 1, SAMPLE_FRAMES).round().astype(int)):
        fj = backbone.features(db.images[j], int(j))
        for i in prior_neighbours(db.poses, int(j), db.config):
            fi = backbone.features(db.images[i], int(i))
            pair, _, _ = backbone.relative_pose(fj, fi, db.camera, images=(db.images[j], db.images[i]))
            if pair is None:
                right.append(False)
                continue
            T_ij = invert_pose(db.poses[i]) @ db.poses[j]
            direction = T_ij[:3, 3] / max(float(np.linalg.norm(T_ij[:3, 3])), 1e-9)
            rotation = np.degrees(rotation_angle(pair.R, T_ij[:3, :3]))
            angle = np.degrees(np.arccos(np.clip(float(pair.t @ direction), -1.0, 1.0)))
            right.append(bool(rotation <= RIGHT_DEG[0] and angle <= RIGHT_DEG[1]))
    return np.array(right, bool)


def sign_test(rootsift: NDArray[np.bool_], xfeat: NDArray[np.bool_]) -> float:
    """One-sided p-value that XFeat gets more of the pairs right than RootSIFT by chance alone:
    a binomial test on the pairs exactly one of them gets right (1 when there are none)."""
    wins, losses = int((xfeat & ~rootsift).sum()), int((rootsift & ~xfeat).sum())
    if wins + losses == 0:
        return 1.0
    return float(binomtest(wins, wins + losses, 0.5, alternative="greater").pvalue)


def _key(fingerprint: str, db_config: DatabaseConfig, config: ClassicalConfig) -> dict[str, Any]:
    alternative = config.switch_config()
    key = {
        "version": _VERSION,
        "fingerprint": fingerprint,
        "sample": [SAMPLE_FRAMES, list(RIGHT_DEG), db_config.prior_baseline, db_config.prior_neighbours],
        "switch": [config.switch_share, SIGNIFICANCE],
        "rootsift": backbone_feature_settings(config) | {"max_error": config.max_epipolar_error},
        "xfeat": backbone_feature_settings(alternative)
        | {"max_error": alternative.xfeat_max_epipolar_error, "refine_window": alternative.refine_window},
    }
    return json.loads(json.dumps(key))


def _cache_file(cache_dir: Path, key: dict[str, Any]) -> Path:
    """One file per key, so that runs with other settings on the same database keep their own."""
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]
    return cache_dir / f"feature_choice-{digest}.json"


def _stored(path: Path, key: dict[str, Any]) -> FeatureChoice | None:
    try:
        stored = json.loads(path.read_text())
        return FeatureChoice(**stored["choice"]) if stored.get("key") == key else None
    except (OSError, ValueError, TypeError, KeyError):
        return None


def cached_choice(
    run_dir: str | os.PathLike, config: ClassicalConfig, db_config: DatabaseConfig | None = None
) -> FeatureChoice | None:
    """The choice :func:`choose_features` stored for the database run at ``run_dir`` (or a build's
    ``database/``) with these settings; None when it has not been made (or the run changed)."""
    from vgpnav_env.perception.database import DatabaseConfig, database_run_dir, index_dir

    path = database_run_dir(run_dir)
    db_config = db_config or DatabaseConfig()
    try:
        key = _key(run_fingerprint(path), db_config, config)
        cache = index_dir(path, db_config)
    except (OSError, ValueError):  # not a readable run
        return None
    return _stored(_cache_file(cache, key), key)


def choose_features(db: Database, config: ClassicalConfig) -> FeatureChoice:
    """The features for a backbone with ``config`` on ``db`` (module docstring): RootSIFT unless it
    gets fewer than ``config.switch_share`` of the database's tested pairs right and XFeat +
    LighterGlue significantly more (:func:`sign_test`). Cached in the database's ``cache_dir``."""
    key = _key(db.fingerprint, db.config, config)
    path = _cache_file(db.cache_dir, key)
    stored = _stored(path, key)
    if stored is not None:
        return stored
    rootsift = pair_outcomes(db, config)
    share = float(rootsift.mean()) if len(rootsift) else 0.0
    choice = FeatureChoice("rootsift", share, None, len(rootsift))
    if share < config.switch_share and len(rootsift):
        xfeat = pair_outcomes(db, config.switch_config())
        p = sign_test(rootsift, xfeat)
        features = "xfeat" if p < SIGNIFICANCE else "rootsift"
        choice = FeatureChoice(features, share, float(xfeat.mean()), len(rootsift), p)
    logger.info("features for %s: %s", db.path, choice.describe())
    text = json.dumps({"key": key, "choice": asdict(choice)}, indent=1)
    atomic_write(path, lambda f: f.write(text.encode()))
    return choice
