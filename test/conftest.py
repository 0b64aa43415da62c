"""Shared fixtures: the Panda's nominal model and config, and a small trained model."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kvark_ros.core.config import load_config
from kvark_ros.core.robot_model import RobotModel

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def panda_config():
    return load_config(ROOT / "config" / "panda.yaml")


@pytest.fixture(scope="session")
def panda(panda_config) -> RobotModel:
    c = panda_config
    return RobotModel(c.urdf, c.joint_names, c.ee_frame, c.flange_frame)


@pytest.fixture(scope="session")
def panda_trained(panda):
    """Residual model and filter tuning from a synthetic free-motion stream (Gaz friction)."""
    from kvark_ros.tools.bench import train_synthetic
    return train_synthetic(panda, "panda", seed=3, duration=20.0)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)
