"""Model-gap workflow (docs/method.md §8): name the physical effects the nominal model lacks."""
from kvark_ros.gap.effects import EFFECT_NAMES, augmentation_gap

__all__ = ["EFFECT_NAMES", "augmentation_gap"]
