"""The classical backbone's scene check: features chosen on the database's own posed pairs."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from eval.perception_runs import classical_features
from vgpnav_env.perception import feature_choice
from vgpnav_env.perception.backbones import ClassicalConfig, make_backbone
from vgpnav_env.perception.database import Database, DatabaseConfig
from vgpnav_env.perception.feature_choice import FeatureChoice, cached_choice, choose_features, sign_test


@pytest.fixture
def database(tiny_build_source: Path, tmp_path: Path) -> Database:
    """The tiny build's database in a private copy (no scene check cached yet)."""
    build = Path(shutil.copytree(tiny_build_source, tmp_path / "build"))
    return Database.open(build, config=DatabaseConfig(prior="none"), progress=False)


def _outcomes(monkeypatch: pytest.MonkeyPatch, rootsift: list[bool], xfeat: list[bool]) -> list[str]:
    """Make :func:`feature_choice.pair_outcomes` return these per-pair outcomes by feature kind;
    the kinds asked."""
    asked: list[str] = []

    def outcomes(db: Database, config: ClassicalConfig, progress: bool = False) -> np.ndarray:
        asked.append(config.features)
        return np.array(rootsift if config.features == "rootsift" else xfeat, bool)

    monkeypatch.setattr(feature_choice, "pair_outcomes", outcomes)
    return asked


def test_rootsift_stays_where_it_gets_the_database_pairs_right(database: Database, monkeypatch) -> None:
    """On the textured tiny build RootSIFT gets most of the database's overlapping pairs right (the
    truth is the database's own poses): no switch, XFeat never tried. The choice is cached beside
    the index and read back without matching again; a changed setting or run is not served it."""
    config = ClassicalConfig(threads=1)
    assert cached_choice(database.path, config) is None
    choice = choose_features(database, config)
    assert choice.features == "rootsift" and choice.xfeat is None
    assert 0.4 <= choice.rootsift <= 0.8 and choice.n_pairs >= 60  # measured 0.58 of 130
    assert len(list((database.path / "index").glob("feature_choice-*.json"))) == 1
    assert cached_choice(database.path, config) == choice
    asked = _outcomes(monkeypatch, [False] * 10, [True] * 10)
    assert choose_features(database, config) == choice and asked == []  # the cache, no matching
    assert cached_choice(database.path, ClassicalConfig(max_keypoints=500)) is None
    # Other settings get their own file (here matched with the stubbed outcomes: XFeat wins 10 of 10).
    other = choose_features(database, ClassicalConfig(threads=1, switch_share=0.9))
    assert other.features == "xfeat" and cached_choice(database.path, config) == choice
    backbone = make_backbone("classical", database=database, threads=1)
    assert backbone.config.features == "rootsift" and backbone.config.uses_fallback


def test_xfeat_on_every_pair_where_rootsift_fails_and_xfeat_does_better(
    database: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    # 100 pairs: RootSIFT 5 right, XFeat 20 (the 5 and 15 more): 15 wins, no loss, p = 0.5 ** 15.
    asked = _outcomes(monkeypatch, [True] * 5 + [False] * 95, [True] * 20 + [False] * 80)
    backbone = make_backbone("classical", database=database, threads=1)
    assert asked == ["rootsift", "xfeat"]
    assert backbone.config.features == "xfeat" and backbone.config.matcher == "lighterglue"
    assert backbone.fallback is None
    choice = cached_choice(database.path, ClassicalConfig(threads=1))
    assert choice == FeatureChoice("xfeat", 0.05, 0.2, 100, pytest.approx(0.5**15))
    line = classical_features({}, choice)
    assert line.startswith("xfeat + lighterglue; scene check: xfeat (database pairs right: RootSIFT 0.05")
    assert line.endswith("of 100, p 3.1e-05)")


def test_rootsift_stays_where_xfeat_is_not_significantly_better_or_the_check_is_off(
    database: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    # 14 against 16 right of 100, on different pairs (14 losses, 16 wins): chance (p 0.43).
    asked = _outcomes(monkeypatch, [True] * 14 + [False] * 86, [False] * 14 + [True] * 16 + [False] * 70)
    assert (
        make_backbone("classical", database=database, threads=1, switch_share=0.3).config.features
        == "rootsift"
    )
    assert asked == ["rootsift", "xfeat"]
    asked.clear()
    assert (
        make_backbone("classical", database=database, threads=1, switch_share=0.0).config.features
        == "rootsift"
    )
    assert asked == []  # off: no check at all
    with pytest.raises(ValueError, match="switch_share"):
        ClassicalConfig(switch_share=1.5)


def test_sign_test_counts_only_the_pairs_the_matchers_disagree_on() -> None:
    both = np.ones(50, bool)
    assert sign_test(both, both) == 1.0  # no disagreement: no evidence
    rootsift = np.r_[np.ones(40, bool), np.zeros(60, bool)]
    xfeat = np.r_[np.ones(40, bool), np.ones(10, bool), np.zeros(50, bool)]  # 10 wins, 0 losses
    assert sign_test(rootsift, xfeat) == pytest.approx(0.5**10)
    assert sign_test(xfeat, rootsift) == 1.0  # losing every disagreement


def test_navigation_reports_name_the_scene_check(database: Database) -> None:
    from eval.navigation import classical_settings

    kwargs = {"database_dir": str(database.path), "backbone_options": {"threads": 1}}
    assert classical_settings("classical", kwargs) == {"features": classical_features({})}  # not made yet
    choose_features(database, ClassicalConfig(threads=1))
    line = classical_settings("classical", kwargs)["features"]
    assert "; scene check: rootsift (database pairs right: RootSIFT 0." in line
    assert classical_settings("simulated", kwargs) == {} and classical_settings("classical", {}) == {}
