"""The classical backbone's scene check: features chosen on the database's own posed pairs."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from eval.perception_runs import classical_features
from vgpnav_env.perception import feature_choice
from vgpnav_env.perception.backbones import ClassicalConfig, make_backbone
from vgpnav_env.perception.database import Database, DatabaseConfig
from vgpnav_env.perception.feature_choice import FeatureChoice, cached_choice, choose_features


@pytest.fixture
def database(tiny_build_source: Path, tmp_path: Path) -> Database:
    """The tiny build's database in a private copy (no scene check cached yet)."""
    build = Path(shutil.copytree(tiny_build_source, tmp_path / "build"))
    return Database.open(build, config=DatabaseConfig(prior="none"), progress=False)


def _shares(monkeypatch: pytest.MonkeyPatch, rootsift: float, xfeat: float) -> list[str]:
    """Make :func:`feature_choice.pair_share` return these shares by feature kind; the kinds asked."""
    asked: list[str] = []

    def share(db: Database, config: ClassicalConfig, progress: bool = False) -> tuple[float, int]:
        asked.append(config.features)
        return (rootsift if config.features == "rootsift" else xfeat), 100

    monkeypatch.setattr(feature_choice, "pair_share", share)
    return asked


def test_rootsift_stays_where_it_gets_the_database_pairs_right(database: Database, monkeypatch) -> None:
    """On the textured tiny build RootSIFT gets most of the database's overlapping pairs right (the
    truth is the database's own poses): no switch, XFeat never tried. The choice is cached beside
    the index and read back without matching again; a changed setting or run is not served it."""
    config = ClassicalConfig(threads=1)
    assert cached_choice(database.path, config) is None
    choice = choose_features(database, config)
    assert choice.features == "rootsift" and choice.xfeat is None
    assert 0.4 <= choice.rootsift <= 1.0 and choice.n_pairs >= 60  # measured 0.58 of 130
    assert (database.path / "index" / "feature_choice.json").is_file()
    assert cached_choice(database.path, config) == choice
    asked = _shares(monkeypatch, 0.0, 1.0)
    assert choose_features(database, config) == choice and asked == []  # the cache, no matching
    assert cached_choice(database.path, ClassicalConfig(max_keypoints=500)) is None
    backbone = make_backbone("classical", database=database, threads=1)
    assert backbone.config.features == "rootsift" and backbone.config.uses_fallback


def test_xfeat_on_every_pair_where_rootsift_fails_and_xfeat_does_better(
    database: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    asked = _shares(monkeypatch, rootsift=0.05, xfeat=0.2)
    backbone = make_backbone("classical", database=database, threads=1)
    assert asked == ["rootsift", "xfeat"]
    assert backbone.config.features == "xfeat" and backbone.config.matcher == "lighterglue"
    assert backbone.fallback is None
    choice = cached_choice(database.path, ClassicalConfig(threads=1))
    assert choice == FeatureChoice("xfeat", 0.05, 0.2, 100)
    line = classical_features({}, choice)
    assert line.startswith("xfeat + lighterglue; scene check: xfeat (database pairs right: RootSIFT 0.05")


def test_rootsift_stays_where_xfeat_does_not_double_it_or_the_check_is_off(
    database: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    asked = _shares(monkeypatch, rootsift=0.14, xfeat=0.16)  # both weak: not worth XFeat's CPU
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
    for bad in ({"switch_share": 1.5}, {"switch_gain": 0.5}):
        with pytest.raises(ValueError, match="switch_share in"):
            ClassicalConfig(**bad)


def test_navigation_reports_name_the_scene_check(database: Database) -> None:
    from eval.navigation import classical_settings

    kwargs = {"database_dir": str(database.path), "backbone_options": {"threads": 1}}
    assert classical_settings("classical", kwargs) == {"features": classical_features({})}  # not made yet
    choose_features(database, ClassicalConfig(threads=1))
    line = classical_settings("classical", kwargs)["features"]
    assert "; scene check: rootsift (database pairs right: RootSIFT 0." in line
    assert classical_settings("simulated", kwargs) == {} and classical_settings("classical", {}) == {}
