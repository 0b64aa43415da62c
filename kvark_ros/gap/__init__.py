"""Model-gap workflow (docs/method.md §8): name the physical effects the nominal model lacks."""
from kvark_ros.core.effect_catalog import EFFECT_NAMES
from kvark_ros.gap.effects import augmentation_gap

__all__ = ["EFFECT_NAMES", "augmentation_gap"]
