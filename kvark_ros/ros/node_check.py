"""``kvark node-check``: the ROS 2 node as users run it, fed a bag over loopback DDS, against ``kvark replay``.

Starts ``estimator_node`` as a process of its own (``python -m kvark_ros.ros.estimator_node --ros-args
--params-file …``, no ament environment needed) on a ROS domain restricted to this machine
(``kvark_ros.ros.node_process``), waits for its first ``/diagnostics`` with the model loaded, plays the bag into
it with ``BagPlayer`` at real time × ``rate`` (optionally calling ``~/reload_model`` at a bag time, without
waiting for the reply, and with ``load_cores`` busy processes beside it), records every τ_ext it publishes, and
compares them with ``run_observer`` (what ``kvark replay`` computes) on the same bag, config and model.

Reported: estimates received of those replay gives, the largest |Δτ_ext| over the samples both have,
the latency of each estimate (its DDS source timestamp minus the system time the player published the joint
state it answers, so the recorder's own delay does not count), the CPU during playback as a fraction of one
core of the node, of this checking process (player and recorder) and of the whole machine (the load present),
the input loss the node itself reported on ``/diagnostics``, and with ``callgrind`` the node's instructions per
estimate (idle work subtracted), a figure other processes on the machine do not change. The recorder takes the
τ_ext topic as the node takes its inputs (``input_loop``), so that it leaves the cores to the node.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from kvark_ros.core.config import NODE_NAME, EstimatorConfig, launch_parameters, load_config
from kvark_ros.core.files import write_text_atomically
from kvark_ros.core.estimation.model_store import load_model
from kvark_ros.core.estimation.pairing import stamp_seconds
from kvark_ros.core.estimation.robot_model import urdf_sha256
from kvark_ros.io.recorded_inputs import read_inputs
from kvark_ros.io.cdr_messages import Decoder
from kvark_ros.io.common import JOINT_STATE
from kvark_ros.ros.input_loop import InputGroup, InputLoop, ServiceThread
from kvark_ros.ros.node_process import Callgrind, Usage, joined, local_domain, spinning, start_node, stop_node
from kvark_ros.ros.player import BagPlayer, Recording, input_recording, playback_rate
from kvark_ros.tools.replay import run_observer

if TYPE_CHECKING:
    from kvark_ros.cli import SubParsers

TOLERANCE = 1e-9            # N·m: the node and replay run the same code on the same numbers
DOMAIN_RANGE = (101, 200)   # ROS_DOMAIN_ID drawn from here (Fast DDS allows at most 232)
IDLE = 5.0                  # s of idling counted after the work with callgrind, to subtract the node's idle work
__all__ = ["Recorder", "check_node", "compare", "main"]


class Recorder(Node):
    """Records the node's τ_ext (with its publication time) and its ``/diagnostics``; calls ``~/reload_model``.
    τ_ext arrives on an :class:`InputLoop` of its own thread, the rest on a :class:`ServiceThread` (``start``)."""

    def __init__(self, node_name: str) -> None:
        super().__init__("kvark_node_check")
        self.torque: list[tuple[float, np.ndarray, int]] = []       # (stamp s, τ_ext, published ns)
        self.diagnostics: list[DiagnosticArray] = []
        self.reload_replies: list[Trigger.Response] = []
        self.lock, group = threading.Lock(), InputGroup()
        self._decoder = Decoder(JOINT_STATE)
        reliable = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self._torque = self.create_subscription(JointState, f"/{node_name}/external_joint_torque", self._on_torque,
                                                reliable, callback_group=group, raw=True)
        self.create_subscription(DiagnosticArray, "/diagnostics", self.diagnostics.append, 10)
        self.reload = self.create_client(Trigger, f"/{node_name}/reload_model")
        self._loop = InputLoop(self, [self._torque], group, self.lock)
        self._service_thread = ServiceThread(self, on_end=self._loop.stop)
        self._torque_thread = threading.Thread(target=self._loop.spin, name="kvark_node_check_torque", daemon=True)

    def _on_torque(self, raw: bytes, info: dict) -> None:
        numbers = self._decoder.decode(raw)[1]
        stamp = stamp_seconds(int(numbers["sec"][0]), int(numbers["nanosec"][0]))
        self.torque.append((stamp, numbers["effort"].copy(), info["source_timestamp"]))

    def start(self) -> None:
        self._service_thread.start()
        self._torque_thread.start()

    def stop(self) -> None:
        self._loop.stop()
        self._torque_thread.join()
        self._service_thread.stop()

    def call_reload(self) -> None:
        """Ask for a reload and return at once; the reply lands in ``reload_replies``."""
        self.reload.call_async(Trigger.Request()).add_done_callback(
            lambda future: self.reload_replies.append(future.result()))

    def model_ready(self, node_name: str) -> bool:
        """Whether the node's newest ``/diagnostics`` says its model is loaded."""
        return any(status.name.endswith(f"{node_name}: model") and status.level == DiagnosticStatus.OK
                   for array in self.diagnostics[-1:] for status in array.status)


def node_parameters_file(config_path: str | os.PathLike, model_dir: str, folder: Path) -> Path:
    """The config file's parameters as the launch file passes them (``launch_parameters``: every key of it that
    applies to the node, relative paths made absolute) with ``model_dir``, as a node parameter file in ``folder``."""
    flat = launch_parameters(config_path)
    flat["residual_model.model_dir"] = str(Path(model_dir).resolve())
    parameters: dict = {}
    for name, value in flat.items():             # dotted names nested again, as the YAML groups them
        *groups, key = name.split(".")
        holder = parameters
        for group in groups:
            holder = holder.setdefault(group, {})
        holder[key] = value
    path = folder / "parameters.yaml"
    write_text_atomically(path, yaml.safe_dump({NODE_NAME: {"ros__parameters": parameters}}, sort_keys=False))
    return path


def check_node(config_path: str, bag: str, model_dir: str | None = None, rate: float = 1.0,
               reload_at: float | None = None, domain_id: int | None = None, start_timeout: float = 120.0,
               log=print, load_cores: int = 0, callgrind: Path | None = None) -> dict:
    """Run the node process on ``bag`` and compare it with replay (module docstring); the figures as a dict.
    ``load_cores`` busy processes run during the playback; ``callgrind``: run the node under callgrind, its output
    files into this folder (give a ``rate`` the node keeps up with under valgrind, e.g. 0.1)."""
    config = load_config(config_path)
    model_dir = model_dir or config.model_dir
    recording = input_recording(bag, config.input)
    domain = domain_id if domain_id is not None else int(np.random.default_rng().integers(*DOMAIN_RANGE))
    counter = None if callgrind is None else Callgrind(Path(callgrind).resolve())
    with tempfile.TemporaryDirectory(prefix="kvark_node_check_") as scratch:
        ros_env = local_domain(domain, Path(scratch) / "log")
        parameters = node_parameters_file(config_path, model_dir, Path(scratch))
        node_log = open(Path(scratch) / "node.log", "w+")
        process = start_node(parameters, {**os.environ, **ros_env}, node_log, counter.prefix if counter else ())
        figures: dict = {}
        try:
            with joined(ros_env):
                figures = _play_and_record(process, recording, rate, reload_at, start_timeout, log, load_cores,
                                           counter)
        except RuntimeError as exc:
            node_log.seek(0)
            raise RuntimeError(f"{exc}; the node's log:\n{node_log.read()[-2000:]}") from exc
        finally:
            figures["node_exit_code"] = stop_node(process, 60.0 if counter else 10.0)
            node_log.seek(0)
            figures["node_log_tail"] = node_log.read()[-2000:]
            node_log.close()
    figures.update(compare(figures.pop("torque"), config, model_dir, bag))
    figures.update(config=str(config_path), bag=str(bag), model=str(model_dir), rate=rate, reload_at=reload_at,
                   domain_id=domain, load_cores=load_cores, cores=os.cpu_count())
    if "instructions" in figures:
        figures["instructions_per_estimate"] = figures.pop("instructions") / max(figures["estimates_received"], 1)
    return figures


def _wait_until(condition, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def _play_and_record(process: subprocess.Popen, recording: Recording, rate: float, reload_at: float | None,
                     start_timeout: float, log, load_cores: int, counter: Callgrind | None) -> dict:
    """Wait for the node, play the recording, keep recording until its outputs stop; the raw figures."""
    recorder, player = Recorder(NODE_NAME), BagPlayer(recording)
    recorder.start()
    try:
        started = time.monotonic()
        ready = _wait_until(lambda: process.poll() is not None or recorder.model_ready(NODE_NAME), start_timeout)
        if process.poll() is not None or not ready:
            raise RuntimeError(f"the node did not come up within {start_timeout:g} s (exit code {process.poll()})")
        player.wait_for_subscribers(10.0)
        reload = "" if reload_at is None else f", ~/reload_model at {reload_at:g} s"
        log(f"[node-check] node up in {time.monotonic() - started:.1f} s; playing {len(recording.messages)} messages, "
            f"{recording.duration:.2f} s at {rate:g}x{reload}" + (f", {load_cores} busy processes beside it"
                                                                  if load_cores else ""))
        reloads = [reload_at] if reload_at is not None else []

        def at(bag_time: float) -> None:
            if reloads and bag_time >= reloads[0]:
                reloads.pop()
                recorder.call_reload()

        usage = Usage(process.pid)
        with spinning(load_cores):
            if counter is not None:
                counter.start(process.pid)
            usage.start()
            late = player.play(rate, at)
            usage.stop()
            count, quiet_since = -1, time.monotonic()
            while time.monotonic() - quiet_since < 1.5:          # until no estimate came for 1.5 s
                time.sleep(0.1)
                if len(recorder.torque) != count:
                    count, quiet_since = len(recorder.torque), time.monotonic()
            counted = counter.instructions(process.pid, IDLE) if counter is not None else None
        seen = len(recorder.diagnostics)                         # one more /diagnostics with the run's last counts
        _wait_until(lambda: len(recorder.diagnostics) > seen, 3.0)
    finally:
        recorder.stop()
        recorder.destroy_node()
    sent = {stamp: player.sent_ns[k] for k, stamp in state_stamps(recording).items()}
    answered = [(stamp, published - sent[stamp]) for stamp, _, published in recorder.torque if stamp in sent]
    latency = np.array([ns for _, ns in answered]) / 1e6
    lost = _diagnostic_value(recorder.diagnostics, "input", "joint_states_lost")
    span = max(sent) - min(sent) if len(sent) > 1 else 0.0
    figures = {"torque": recorder.torque, "player_late_ms": late * 1e3, "node_cpu_cores": usage.node,
               "input_rate_hz": (len(sent) - 1) / span * rate if span > 0.0 else None,
               "checker_cpu_cores": usage.checker, "machine_cpu_cores": usage.machine,
               "latency_ms_p50": float(np.percentile(latency, 50)) if latency.size else None,
               "latency_ms_p99": float(np.percentile(latency, 99)) if latency.size else None,
               "latency_ms_max": float(latency.max()) if latency.size else None,
               "latency_ms_max_at_s": (answered[int(latency.argmax())][0] - min(sent)) if latency.size else None,
               "node_reported_lost": None if lost is None else int(lost),
               "reload_replies": [(reply.success, reply.message) for reply in recorder.reload_replies]}
    if counted is not None:
        figures.update(instructions=counted[0], idle_instructions_per_s=counted[1])
    return figures


def state_stamps(recording: Recording) -> dict[int, float]:
    """Message index -> header stamp (s) of every joint state of the recording (its first topic)."""
    decoder = Decoder(JOINT_STATE)
    stamps = {}
    for k, (_, topic, raw) in enumerate(recording.messages):
        if topic == 0:
            numbers = decoder.decode(raw)[1]
            stamps[k] = stamp_seconds(int(numbers["sec"][0]), int(numbers["nanosec"][0]))
    return stamps


def _diagnostic_value(arrays: list[DiagnosticArray], status_name: str, key: str) -> str | None:
    for array in reversed(arrays):
        for status in array.status:
            if status.name.endswith(f": {status_name}"):
                return next((kv.value for kv in status.values if kv.key == key), None)
    return None


def compare(torque: list, config: EstimatorConfig, model_dir: str, bag: str) -> dict:
    """The node's τ_ext (``torque``: (stamp s, τ_ext, …) per estimate) against replay's on the same samples of
    ``bag``: counts and the largest difference."""
    trained = load_model(model_dir, config.joint_names, urdf_sha256(config.urdf))
    inputs = read_inputs(bag, config)[1]
    expected = run_observer(config, trained, inputs, config.observer)
    stamps = inputs.stamp[expected.valid]
    by_stamp = {stamp: tau for stamp, tau, _ in torque}
    common = [k for k, stamp in enumerate(stamps) if stamp in by_stamp]
    got = np.array([by_stamp[stamps[k]] for k in common]).reshape(-1, config.n_joints)
    difference = np.abs(got - expected.tau_ext[expected.valid][common])
    return {"estimates_expected": int(len(stamps)), "estimates_received": len(torque),
            "estimates_matched": len(common), "duplicates": len(torque) - len(by_stamp),
            "max_abs_difference": float(difference.max()) if difference.size else None}


def passed(figures: dict) -> bool:
    """Every replay estimate came, nothing else, each within ``TOLERANCE``, every reload succeeded, and the node
    ended with exit code 0 on SIGTERM."""
    return (figures["estimates_received"] == figures["estimates_matched"] == figures["estimates_expected"]
            and figures["max_abs_difference"] is not None and figures["max_abs_difference"] <= TOLERANCE
            and all(success for success, _ in figures["reload_replies"]) and figures["node_exit_code"] == 0)


def summary(figures: dict) -> str:
    """The figures in three lines."""
    reload = "" if figures["reload_at"] is None else f", ~/reload_model at {figures['reload_at']:g} s: " + (
        "; ".join(f"{'ok' if ok else 'FAILED'} ({message})" for ok, message in figures["reload_replies"])
        or "no reply")
    def number(key: str, form: str = ".2f") -> str:
        return "n/a" if figures[key] is None else format(figures[key], form)

    return (f"[node-check] {figures['estimates_matched']} of {figures['estimates_expected']} estimates "
            f"({figures['estimates_received']} received), max |τ_node − τ_replay| "
            f"{number('max_abs_difference', '.2e')} N·m at {figures['rate']:g}x{reload}\n"
            f"[node-check] latency p50 {number('latency_ms_p50')} ms, p99 {number('latency_ms_p99')} ms, "
            f"max {number('latency_ms_max')} ms (at {number('latency_ms_max_at_s')} s); the node reported "
            f"{figures['node_reported_lost']} joint states lost; on SIGTERM it exited with code "
            f"{figures['node_exit_code']}\n"
            f"[node-check] CPU during playback: node {figures['node_cpu_cores']:.3f} core, node-check "
            f"{figures['checker_cpu_cores']:.3f}, the machine {figures['machine_cpu_cores']:.2f} of "
            f"{figures['cores']} cores ({figures['load_cores']} busy processes beside them)\n"
            + (f"[node-check] node instructions per estimate {figures['instructions_per_estimate'] / 1e3:.0f} k "
               f"(callgrind, less its idle {figures['idle_instructions_per_s'] / 1e6:.2f} M/s)\n"
               if "instructions_per_estimate" in figures else "")
            + f"[node-check] {'MATCH: the node equals replay on every sample' if passed(figures) else 'MISMATCH'}")


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser(
        "node-check", help="run the ROS 2 node on a bag over loopback DDS and compare it with replay (rclpy)",
        description="Start the estimator node as a process (as shipped, on a ROS domain of its own restricted to "
                    "this machine), play BAG into it at real time x --rate, optionally call ~/reload_model "
                    "mid-run, and compare every τ_ext it publishes with what `kvark replay` computes. Prints the "
                    "match, the latency p50/p99/max, the input the node lost, the CPU of the node, of node-check "
                    "and of the machine during playback, and the node's exit code on SIGTERM; exit code 1 on a "
                    "mismatch or when the node does not exit with 0.")
    parser.add_argument("--config", required=True, help="estimator config YAML (the node's parameter file)")
    parser.add_argument("--model", help="model directory (default: residual_model.model_dir of the config)")
    parser.add_argument("--bag", required=True, help="bag to play (its joint states and effort commands)")
    parser.add_argument("--rate", type=playback_rate, default=1.0,
                        help="playback speed (1 = real time, 2 = twice as fast)")
    parser.add_argument("--reload-at", type=float, metavar="SECONDS",
                        help="call ~/reload_model when the bag reaches SECONDS (the reply is not waited for)")
    parser.add_argument("--domain-id", type=int, help=f"ROS_DOMAIN_ID to use (default: drawn from "
                                                      f"{DOMAIN_RANGE[0]}-{DOMAIN_RANGE[1] - 1})")
    parser.add_argument("--load-cores", type=busy_processes, default=0, metavar="N",
                        help="keep N other processes busy during playback (1 on a 2-core machine: the other core "
                             "fully loaded, as on a robot computer running its controller)")
    parser.add_argument("--callgrind", type=Path, metavar="DIR",
                        help="run the node under valgrind's callgrind (output files into DIR) and print its "
                             "instructions per estimate, idle work subtracted; play at a rate it keeps up with "
                             "there, e.g. --rate 0.1")
    parser.add_argument("--json", help="also write the figures to this JSON file")
    parser.set_defaults(run=run)


def busy_processes(text: str) -> int:
    """``--load-cores``: a count of busy processes, 0 or more (argparse type)."""
    if not text.isdigit():
        raise argparse.ArgumentTypeError(f"must be a whole number >= 0, got {text!r}")
    return int(text)


def run(args: argparse.Namespace) -> int:
    if args.callgrind is not None:
        args.callgrind.mkdir(parents=True, exist_ok=True)
    figures = check_node(args.config, args.bag, args.model, args.rate, args.reload_at, args.domain_id,
                         start_timeout=600.0 if args.callgrind else 120.0, load_cores=args.load_cores,
                         callgrind=args.callgrind)
    print(summary(figures), flush=True)
    if args.json:
        write_text_atomically(Path(args.json), json.dumps(figures, indent=1) + "\n")
    if not passed(figures):
        print(f"[node-check] the node's log ends with:\n{figures['node_log_tail']}", file=sys.stderr)
    return 0 if passed(figures) else 1


def main() -> int:
    """``python -m kvark_ros.ros.node_check …``: ``kvark node-check …``, with its error handling."""
    from kvark_ros.cli import main as kvark
    return kvark(["node-check", *sys.argv[1:]])


if __name__ == "__main__":
    sys.exit(main())
