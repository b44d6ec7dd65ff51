"""Verification decides from size-free evidence: the same query frames of the tiny build rendered at
two image sizes get the same accept / lost decisions, with the rules and with the calibrated model."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_pipeline import FAST_VLAD
from tiny_build import QUERY_HEIGHT, make_tiny_build

from vgpnav_env.perception.database import Database, DatabaseConfig
from vgpnav_env.perception.pipeline import Perceiver, PerceptionConfig
from vgpnav_env.perception.verify import VerifyConfig, default_model
from vgpnav_env.runs import load_run

SIZES = ((160, 120), (320, 240))


@pytest.fixture(scope="module")
def builds(tmp_path_factory: pytest.TempPathFactory) -> dict[tuple[int, int], Path]:
    root = tmp_path_factory.mktemp("sizes")
    return {size: make_tiny_build(root / f"{size[0]}x{size[1]}", size) for size in SIZES}


def _decisions(build: Path, decision: str) -> list[str]:
    database = Database.open(build, config=DatabaseConfig(vlad=FAST_VLAD, prior="none"), progress=False)
    run = load_run(build / "query")
    config = PerceptionConfig(camera_height=QUERY_HEIGHT, verify=VerifyConfig(decision=decision))
    perceiver = Perceiver(database, "classical", config=config)
    perceiver.initialize(run.images[:1])
    return [perceiver.perceive(rgb).status for rgb in run.images]


@pytest.mark.parametrize("decision", ["rules", "model"])
def test_two_image_sizes_give_the_same_decisions(builds, decision: str) -> None:
    if decision == "model" and default_model() is None:
        pytest.skip("no calibrated model installed")
    small, large = (_decisions(builds[size], decision) for size in SIZES)
    assert small == large
    assert np.mean([s == "localized" for s in small]) >= 0.5  # not a run that decides nothing
