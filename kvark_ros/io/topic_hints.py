"""The one-line error for a topic the config names that a bag lacks: the config key that names it, the bag's topics
of the message type it needs, and the nearest of them (a recording whose topics were remapped: ``/arm/joint_states``
where the config says ``joint_states``)."""

from __future__ import annotations

from typing import Iterable, Mapping

from kvark_ros.core.hints import listing, nearest
from kvark_ros.io.common import PathLike
from kvark_ros.io.runs import BagError, bag_error

__all__ = ["missing_topic"]


def missing_topic(path: PathLike, problem: str, topic: str, key: str, types: Mapping[str, Iterable[str]],
                  allowed: Iterable[str], exclude: Iterable[str] = ()) -> BagError:
    """``<path>: <problem>; <fix>``, ``problem`` saying that ``topic`` (set by the config ``key``) is absent or
    empty. The fix lists the bag's topics of an ``allowed`` message type (``types``: topic → its types), except
    ``exclude`` (the run's other topics), and names the nearest of them (the only one, if no other is near)."""
    wanted, skipped = set(allowed), set(exclude) | {topic}
    kinds = " or ".join(sorted(name.rpartition("/")[2] for name in wanted))
    candidates = sorted(name for name, found in types.items() if wanted & set(found) and name not in skipped)
    if not candidates:
        other = " other" if any(wanted & set(found) for name, found in types.items() if name in skipped) else ""
        return bag_error(path, f"{problem}, and the bag has no{other} {kinds} topic (its topics: "
                               f"{listing(sorted(types)) or 'none'})",
                         f"record it, or set {key} to the topic that has it")
    guess = nearest(topic, candidates) or (candidates[0] if len(candidates) == 1 else None)
    fix = f"set {key} to one of them" if guess is None else f"did you mean {guess!r}? set {key}: {guess}"
    return bag_error(path, f"{problem}; the bag's {kinds} topics: {listing(candidates)}", fix)
