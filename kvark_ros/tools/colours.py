"""One colour per observer, the same in every figure, and the word for it in reports.

The colour follows the observer's place in the catalog (``kvark_ros.core.observer_catalog``), not the order in
which a figure happens to draw its observers, so kf is the same orange in the time histories, the reliability
diagram and the bars. The palette is matplotlib's ten Tableau colours without grey, then five named colours that
stay apart from them (CIE76 ΔE ≥ 25 between any two, and from black): enough for every observer of the catalog.
Black is the ground truth's alone.
"""
from __future__ import annotations

from kvark_ros.core.observer_catalog import OBSERVER_NAMES

TRUTH_COLOUR = "black"
PALETTE = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:olive",
           "tab:cyan", "navy", "teal", "lime", "gold", "magenta")
UNLISTED_COLOUR = "tab:gray"    # an observer name the catalog does not hold (a test's, a renamed one)
OBSERVER_COLOURS = dict(zip(OBSERVER_NAMES, PALETTE))
if len(OBSERVER_COLOURS) < len(OBSERVER_NAMES):
    raise RuntimeError(f"colours.PALETTE has {len(PALETTE)} colours for {len(OBSERVER_NAMES)} observers; add some")


def observer_colour(name: str) -> str:
    """The matplotlib colour of observer ``name``."""
    return OBSERVER_COLOURS.get(name, UNLISTED_COLOUR)


def colour_word(name: str) -> str:
    """The colour of observer ``name`` in words, for report text (``"tab:orange"`` reads ``"orange"``)."""
    return observer_colour(name).removeprefix("tab:")
