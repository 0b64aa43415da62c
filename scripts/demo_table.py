"""The short table `make demo` ends with: joint RMSE / coverage95 per scene of kvark, kf, momentum and the best
other observer, read off the replays' metrics.json.

    python scripts/demo_table.py RESULTS_DIR
"""
from __future__ import annotations

import sys
from pathlib import Path

from results_doc import SCENES, keep_scenes, read_json, scene_table

SHOWN = ("kvark", "kf", "momentum")


def demo_table(results: Path) -> str:
    scenes = keep_scenes({scene: read_json(results / scene / "metrics.json") for scene in SCENES})
    best = {min((name for name in observers if name not in SHOWN + ("oracle",)),
                key=lambda name: observers[name]["joint_rmse"]) for observers in scenes.values()}
    shown = {scene: {name: observers[name] for name in (*SHOWN, *sorted(best)) if name in observers}
             for scene, observers in scenes.items()}
    return (f"Joint RMSE of τ_ext (N·m) / coverage95 (the lowest joint's); every observer and metric: "
            f"{results}/<scene>/report.md\n\n" + scene_table(shown))


if __name__ == "__main__":
    print(demo_table(Path(sys.argv[1] if len(sys.argv) > 1 else "results")))
