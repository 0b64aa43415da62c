"""Model-gap workflow (DESIGN §6): name the physical effects the nominal model lacks."""
from kvark_ros.gap.effects import EFFECT_NAMES, augmentation_gap

__all__ = ["EFFECT_NAMES", "augmentation_gap"]
