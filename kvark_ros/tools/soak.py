"""``kvark soak``: a long run of the Estimator on faulty synthetic data, with reliability figures.

Steps one Estimator ``--steps`` times (default 10⁶, over half an hour of 500 Hz data) on a
synthetic stream of the configured robot with contacts (step and ramp external torques that
switch on and off) and injected faults: gaps longer than ``input.max_gap`` (the filter resets),
samples with NaN or Inf, out-of-order and duplicate stamps, and samples of the wrong length.
Every ``--check-every`` steps it checks that the observer's state covariance is symmetric
positive definite; every output is checked for NaN/Inf. The resident set size is sampled at
each check, so the growth between the first and the last 10 % of the run shows whether memory
stays flat. Progress lines go to stdout; the last line is one JSON object. The exit code is
non-zero if any output was non-finite, any step raised, or a covariance was not SPD.

The stream is a 20 s synthetic free-motion segment (``kvark_ros.tools.synthetic``) replayed
with increasing stamps; each replay starts after a gap (the trajectory jumps back), and the
external torque is added to the measured torque on the fly, so memory does not grow with
``--steps``.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import resource
import sys
import time
import traceback
from collections import Counter
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

import numpy as np

from kvark_ros.core.config import EstimatorConfig, default_config_path, load_config
from kvark_ros.core.estimation.estimator import Estimator, Status
from kvark_ros.core.estimation.model_store import TrainedModel
from kvark_ros.core.estimation.observers import LEARNED_BASELINE_VARIANTS, make_observer
from kvark_ros.core.estimation.robot_model import RobotModel
from kvark_ros.tools.synthetic import synthetic_stream

if TYPE_CHECKING:
    from kvark_ros.cli import SubParsers

RATE = 500.0                 # Hz, sample rate of the synthetic stream
SEGMENT_SECONDS = 20.0       # length of the replayed free-motion segment
SYMMETRY_TOLERANCE = 1e-9    # relative

# Fault kinds and the Estimator status each one must produce.
NAN = "nan"
INF = "inf"
OUT_OF_ORDER = "out_of_order"
DUPLICATE = "duplicate"
BAD_SHAPE = "bad_shape"
GAP = "gap"
WRAP = "gap_at_replay"          # the segment starts again after a gap: the trajectory jumps back
EXPECTED_STATUS = {NAN: Status.NON_FINITE, INF: Status.NON_FINITE, OUT_OF_ORDER: Status.STAMP_NOT_INCREASING,
                   DUPLICATE: Status.STAMP_NOT_INCREASING, BAD_SHAPE: Status.BAD_SHAPE, GAP: Status.GAP_RESET,
                   WRAP: Status.GAP_RESET}
# Per-sample probabilities of each injected fault (gaps: per sample, then 30-150 samples skipped).
FAULT_RATES = {NAN: 1e-3, INF: 2e-4, OUT_OF_ORDER: 5e-4, DUPLICATE: 2e-4, BAD_SHAPE: 1e-4, GAP: 3e-4}


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser(
        "soak", help="long faulty run of the estimator: NaN, crashes, covariance SPD, memory",
        description="Step the Estimator on a long synthetic stream with contacts, gaps longer than "
                    "input.max_gap, NaN/Inf samples, out-of-order and duplicate stamps; check that every "
                    "output is finite and the observer covariance stays symmetric positive definite, and "
                    "that memory stays flat. The last line is one JSON object; the exit code is non-zero "
                    "on any NaN output, crash or non-SPD covariance.")
    parser.add_argument("--robot", default="panda", help="robot whose config/<robot>.yaml is used (default: panda)")
    parser.add_argument("--config", help="config YAML (default: the robot's shipped config)")
    parser.add_argument("--observer", help="observer name (default: the config's observer)")
    parser.add_argument("--steps", type=int, default=10 ** 6, help="Estimator.step calls (default 1000000)")
    parser.add_argument("--check-every", type=int, default=10 ** 4,
                        help="steps between covariance and memory checks (default 10000)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    if args.steps <= 0 or args.check_every <= 0:
        raise SystemExit("kvark soak: --steps and --check-every must be positive")
    config = load_config(args.config or default_config_path(args.robot))
    observer = args.observer or config.observer
    robot = RobotModel.from_config(config)
    from kvark_ros.tools.synthetic import train_synthetic
    print(f"training a residual model on a 20 s synthetic free-motion stream of {config.robot} ...", flush=True)
    trained = train_synthetic(robot, config.robot, seed=args.seed, baselines=observer in LEARNED_BASELINE_VARIANTS)
    result = soak(config, robot, trained, steps=args.steps, observer=observer, seed=args.seed,
                  check_every=args.check_every, log=lambda line: print(line, flush=True))
    print(json.dumps(result.summary()))
    if result.failures():
        print("kvark soak: FAILED: " + "; ".join(result.failures()), file=sys.stderr)
        return 1
    return 0


# --------------------------------------------------------------------------- figures


def current_rss_mb() -> float:
    """Resident set size now, MB (from /proc; the peak from getrusage where /proc is absent)."""
    try:
        with open("/proc/self/statm") as statm:
            return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20
    except (OSError, ValueError, IndexError):
        return peak_rss_mb()


def peak_rss_mb() -> float:
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2 ** 20 if sys.platform == "darwin" else peak / 2 ** 10     # bytes on macOS, KiB on Linux


def state_covariances(estimator: Estimator) -> list[np.ndarray]:
    """The observer's state covariance: the 2×2 blocks [p, τ] per joint, or the filter's P; [] if none."""
    observer = estimator.observer
    if hasattr(observer, "covariance_blocks"):
        return list(observer.covariance_blocks())
    P = getattr(observer, "P", None)
    return [] if P is None else [np.asarray(P)]


def check_spd(matrices: list[np.ndarray]) -> tuple[float, float, float]:
    """(smallest eigenvalue, smallest eigenvalue / largest, largest relative asymmetry) over ``matrices``.

    (inf, inf, 0) if there are none; NaN if a matrix is not finite.
    """
    min_eig, min_ratio, asymmetry = math.inf, math.inf, 0.0
    for matrix in matrices:
        if not np.isfinite(matrix).all():
            return math.nan, math.nan, math.nan
        scale = max(1.0, float(np.abs(matrix).max()))
        asymmetry = max(asymmetry, float(np.abs(matrix - matrix.T).max()) / scale)
        eig = np.linalg.eigvalsh(0.5 * (matrix + matrix.T))
        min_eig = min(min_eig, float(eig[0]))
        min_ratio = min(min_ratio, float(eig[0] / eig[-1]) if eig[-1] > 0.0 else -math.inf)
    return min_eig, min_ratio, asymmetry


@dataclass
class SoakResult:
    steps: int = 0
    faults: Counter = field(default_factory=Counter)          # injected, by kind
    misclassified: Counter = field(default_factory=Counter)   # fault kind -> times the status did not name it
    statuses: Counter = field(default_factory=Counter)        # Estimator.counts at the end
    crashes: int = 0
    first_crash: str = ""
    nan_outputs: int = 0
    outputs: int = 0
    checks: int = 0
    min_eig_P: float = math.inf
    min_eig_ratio_P: float = math.inf                         # smallest eigenvalue / largest, per matrix
    max_asymmetry: float = 0.0
    non_spd_checks: int = 0
    peak_rss_mb: float = 0.0
    rss_first_mb: float = 0.0
    rss_last_mb: float = 0.0
    seconds: float = 0.0
    observer: str = ""
    contacts: int = 0

    @property
    def rss_growth_mb(self) -> float:
        return self.rss_last_mb - self.rss_first_mb

    def failures(self) -> list[str]:
        out = []
        if self.nan_outputs:
            out.append(f"{self.nan_outputs} non-finite outputs")
        if self.crashes:
            out.append(f"{self.crashes} crashes (first: {self.first_crash.strip().splitlines()[-1]})")
        if self.non_spd_checks or not (self.min_eig_P > 0.0):
            out.append(f"observer covariance not SPD at {self.non_spd_checks} checks (min eigenvalue "
                       f"{self.min_eig_P}, asymmetry {self.max_asymmetry})")
        return out

    def summary(self) -> dict:
        rejected = {status: count for status, count in sorted(self.statuses.items()) if status != Status.OK}
        return {
            "observer": self.observer, "steps": self.steps, "faults_injected": sum(self.faults.values()),
            "faults_by_kind": dict(sorted(self.faults.items())), "contacts": self.contacts,
            "rejected": rejected, "misclassified": dict(self.misclassified), "outputs": self.outputs,
            "crashes": self.crashes, "nan_outputs": self.nan_outputs, "checks": self.checks,
            "min_eig_P": None if math.isinf(self.min_eig_P) else self.min_eig_P,
            "min_eig_ratio_P": None if math.isinf(self.min_eig_ratio_P) else self.min_eig_ratio_P,
            "max_asymmetry_P": self.max_asymmetry, "peak_rss_mb": round(self.peak_rss_mb, 1),
            "rss_growth_mb": round(self.rss_growth_mb, 2), "seconds": round(self.seconds, 1),
            "us_per_step": round(1e6 * self.seconds / max(self.steps, 1), 1),
        }


# --------------------------------------------------------------------------- the run


def _contact_profile(stamp: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """Scalar external-torque profile in [0, 1] over ``stamp``: steps and ramps switching on and off."""
    profile = np.zeros(len(stamp))
    t, end, contacts = stamp[0] + rng.uniform(0.5, 3.0), stamp[-1], 0
    while t < end:
        duration = rng.uniform(0.3, 3.0)
        ramp = rng.uniform(0.1, 0.5 * duration) if rng.random() < 0.5 else 0.0    # step (0) or ramp
        inside = (stamp >= t) & (stamp < t + duration)
        level = np.minimum((stamp[inside] - t) / ramp, 1.0) if ramp > 0.0 else 1.0
        profile[inside] = level
        contacts += 1
        t += duration + rng.uniform(0.5, 3.0)
    return profile, contacts


def _fault_plan(length: int, rng: np.random.Generator) -> dict[int, str]:
    """Sample index -> fault kind for one replay of the segment (at most one fault per sample)."""
    plan: dict[int, str] = {}
    for kind, rate in FAULT_RATES.items():
        for k in np.flatnonzero(rng.random(length) < rate):
            plan.setdefault(int(k), kind)
    return plan


def soak(config: EstimatorConfig, robot: RobotModel, trained: TrainedModel, steps: int = 10 ** 6,
         observer: str | None = None, seed: int = 0, check_every: int = 10 ** 4,
         log: Callable[[str], None] | None = None, progress_lines: int = 10) -> SoakResult:
    """Step a fresh Estimator ``steps`` times on the faulty stream; the figures as a ``SoakResult``."""
    name = observer or config.observer
    estimator = Estimator(config, robot, make_observer(name, trained, config.filter))
    rng = np.random.default_rng(seed + 7919)
    base = synthetic_stream(robot, min(SEGMENT_SECONDS, steps / RATE + 1.0), rate=RATE, seed=seed + 4242)
    length, n, dt = len(base.stamp), robot.n, 1.0 / RATE
    amplitude = np.linspace(3.0, 0.5, n)            # N·m per joint at full contact
    result = SoakResult(observer=name)
    first_window = max(1, steps // 10)
    last_window_start = steps - first_window
    rss_first: list[float] = []
    rss_last: list[float] = []
    progress_every = max(check_every, steps // max(progress_lines, 1))
    wrong_shape = np.zeros(n + 1)
    offset = 0.0                                     # stamp of the replay's first sample
    step = 0
    last_good_stamp: float | None = None
    start = time.perf_counter()

    def check() -> None:
        result.checks += 1
        min_eig, min_ratio, asymmetry = check_spd(state_covariances(estimator))
        if not (min_eig > 0.0 and asymmetry <= SYMMETRY_TOLERANCE):
            result.non_spd_checks += 1
        result.min_eig_P = min_eig if math.isnan(min_eig) else min(result.min_eig_P, min_eig)
        result.min_eig_ratio_P = min_ratio if math.isnan(min_ratio) else min(result.min_eig_ratio_P, min_ratio)
        result.max_asymmetry = max(result.max_asymmetry, asymmetry) if not math.isnan(asymmetry) else math.nan
        rss = current_rss_mb()
        if step <= first_window:
            rss_first.append(rss)
        if step >= last_window_start:
            rss_last.append(rss)

    while step < steps:
        profile, contacts = _contact_profile(base.stamp, rng)
        result.contacts += contacts
        tau_m_all = base.tau_m - profile[:, None] * amplitude[None, :]      # τ_m = ID + τ_f − τ_ext
        stamps = offset + base.stamp
        plan = _fault_plan(length, rng)
        if step > 0:
            plan[0] = WRAP
        k = 0
        while k < length and step < steps:
            kind = plan.pop(k, None)           # an out-of-order sample is extra: sample k follows it
            stamp, q, qd, tau_m = float(stamps[k]), base.q[k], base.qd[k], tau_m_all[k]
            if kind is None or kind == WRAP:
                pass
            elif kind == GAP:
                k += int(rng.integers(int(config.input.max_gap * RATE) + 5, int(config.input.max_gap * RATE) + 125))
                if k >= length:
                    break
                stamp, q, qd, tau_m = float(stamps[k]), base.q[k], base.qd[k], tau_m_all[k]
            elif kind in (NAN, INF):
                field_index = int(rng.integers(4))
                value = math.nan if kind == NAN else (math.inf if rng.random() < 0.5 else -math.inf)
                if field_index == 0:
                    stamp = value
                else:
                    arrays = [q.copy(), qd.copy(), tau_m.copy()]
                    arrays[field_index - 1][int(rng.integers(n))] = value
                    q, qd, tau_m = arrays
            elif kind in (OUT_OF_ORDER, DUPLICATE):
                if last_good_stamp is None:
                    kind = None
                else:                                # an extra, old sample; the current one follows
                    stamp = last_good_stamp - (0.0 if kind == DUPLICATE else dt * int(rng.integers(1, 20)))
            elif kind == BAD_SHAPE:
                q = wrong_shape
            if kind is not None:
                result.faults[kind] += 1
            try:
                estimate = estimator.step(stamp, q, qd, tau_m)
            except Exception:                        # noqa: BLE001 - a crash is a figure here
                result.crashes += 1
                if not result.first_crash:
                    result.first_crash = traceback.format_exc()
                estimate = None
            step += 1
            if kind is not None and estimator.status != EXPECTED_STATUS[kind]:
                result.misclassified[kind] += 1
            if kind not in (OUT_OF_ORDER, DUPLICATE):
                k += 1
            if estimator.status in (Status.OK, Status.WARMUP, Status.GAP_RESET):
                last_good_stamp = stamp
            elif estimator.status == Status.DIVERGED_RESET:
                last_good_stamp = None
            if estimate is not None:
                result.outputs += 1
                total = estimate.tau_ext.sum() + estimate.wrench.sum()
                if estimate.tau_cov is not None:
                    total += estimate.tau_cov.sum()
                if estimate.wrench_cov is not None:
                    total += estimate.wrench_cov.sum()
                if not math.isfinite(total):
                    result.nan_outputs += 1
            if step % check_every == 0 or step == steps:
                check()
                if log is not None and (step % progress_every == 0 or step == steps):
                    elapsed = time.perf_counter() - start
                    log(f"soak {step:>9}/{steps} steps  {elapsed:7.1f} s  {1e6 * elapsed / step:6.1f} µs/step  "
                        f"faults {sum(result.faults.values()):>6}  crashes {result.crashes}  "
                        f"nan {result.nan_outputs}  min eig P {result.min_eig_P:.3e}  "
                        f"rss {current_rss_mb():.1f} MB")
        offset = float(stamps[-1]) + dt + config.input.max_gap + rng.uniform(0.01, 0.5)   # the wrap is a gap
    result.seconds = time.perf_counter() - start
    result.steps = step
    result.statuses = Counter(estimator.counts)
    result.peak_rss_mb = peak_rss_mb()
    result.rss_first_mb = max(rss_first) if rss_first else current_rss_mb()
    result.rss_last_mb = max(rss_last) if rss_last else current_rss_mb()
    return result


def main(argv: list[str] | None = None) -> int:
    """``python -m kvark_ros.tools.soak`` without the ``kvark`` entry point."""
    parser = argparse.ArgumentParser(prog="kvark")
    add_parser(parser.add_subparsers())
    args = parser.parse_args(["soak", *(sys.argv[1:] if argv is None else argv)])
    return args.run(args)


if __name__ == "__main__":
    sys.exit(main())
