"""``kvark node-check``: the ROS 2 node as users run it, fed a bag over loopback DDS, against ``kvark replay``.

Starts ``estimator_node`` as a process of its own (``python -m kvark_ros.ros.estimator_node --ros-args
--params-file …``, no ament environment needed) on a ROS domain restricted to this machine
(``ROS_DOMAIN_ID``, ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, a temporary ``ROS_LOG_DIR``), waits for
its first ``/diagnostics`` with the model loaded, plays the bag into it with ``BagPlayer`` at real time ×
``rate`` (optionally calling ``~/reload_model`` at a bag time, without waiting for the reply), records
every τ_ext it publishes, and compares them with ``run_observer`` (what ``kvark replay`` computes) on the
same bag, config and model.

Reported: estimates received of those replay gives, the largest |Δτ_ext| over the samples both have,
the latency of each estimate (its DDS source timestamp minus the system time the player published the joint
state it answers, so the recorder's own delay does not count), the node's CPU during playback as a
fraction of one core (``/proc``, Linux), and the input loss the node itself reported on ``/diagnostics``.
"""
from __future__ import annotations

import argparse
import json
import os
import struct
import subprocess
import sys
import tempfile
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from kvark_ros.core.config import NODE_NAME, EstimatorConfig, load_config
from kvark_ros.core.files import write_text_atomically
from kvark_ros.core.estimation.model_store import load_model
from kvark_ros.core.estimation.pairing import stamp_seconds
from kvark_ros.core.estimation.robot_model import urdf_sha256
from kvark_ros.io.alignment import read_inputs
from kvark_ros.ros.player import BagPlayer, playback_rate, read_recording
from kvark_ros.tools.replay import run_observer

if TYPE_CHECKING:
    from kvark_ros.cli import SubParsers

TOLERANCE = 1e-9            # N·m: the node and replay run the same code on the same numbers
DOMAIN_RANGE = (101, 200)   # ROS_DOMAIN_ID drawn from here (Fast DDS allows at most 232)
__all__ = ["Recorder", "check_node", "main"]


class Recorder(Node):
    """Records the node's τ_ext (with its publication time) and its ``/diagnostics``; calls ``~/reload_model``."""

    def __init__(self, node_name: str) -> None:
        super().__init__("kvark_node_check")
        self.torque: list[tuple[float, list[float], int]] = []       # (stamp s, τ_ext, published ns)
        self.diagnostics: list[DiagnosticArray] = []
        self.reload_replies: list[Trigger.Response] = []
        reliable = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.create_subscription(JointState, f"/{node_name}/external_joint_torque", self._on_torque, reliable)
        self.create_subscription(DiagnosticArray, "/diagnostics", self.diagnostics.append, 10)
        self.reload = self.create_client(Trigger, f"/{node_name}/reload_model")

    def _on_torque(self, msg: JointState, info: dict) -> None:
        stamp = stamp_seconds(msg.header.stamp.sec, msg.header.stamp.nanosec)
        self.torque.append((stamp, list(msg.effort), info["source_timestamp"]))

    def call_reload(self) -> None:
        """Ask for a reload and return at once; the reply lands in ``reload_replies``."""
        self.reload.call_async(Trigger.Request()).add_done_callback(
            lambda future: self.reload_replies.append(future.result()))

    def model_ready(self, node_name: str) -> bool:
        """Whether the node's newest ``/diagnostics`` says its model is loaded."""
        return any(status.name.endswith(f"{node_name}: model") and status.level == DiagnosticStatus.OK
                   for array in self.diagnostics[-1:] for status in array.status)


def node_parameters_file(config_path: str | os.PathLike, config: EstimatorConfig, model_dir: str,
                         folder: Path) -> Path:
    """The config file's parameters with absolute paths and ``model_dir``, as a node parameter file in ``folder``."""
    document = yaml.safe_load(Path(config_path).read_text())
    parameters = document[NODE_NAME]["ros__parameters"]
    parameters.setdefault("residual_model", {})["model_dir"] = str(Path(model_dir).resolve())
    parameters.setdefault("robot_model", {})["urdf"] = config.urdf
    parameters["model_augmentation"] = config.model_augmentation
    path = folder / "parameters.yaml"
    write_text_atomically(path, yaml.safe_dump(document, sort_keys=False))
    return path


def local_domain(domain: int, log_dir: Path) -> dict[str, str]:
    """The variables that put a ROS 2 process on domain ``domain``, on this machine only, logging to ``log_dir``."""
    return {"ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_LOG_DIR": str(log_dir)}


def start_node(parameters: Path, env: dict[str, str], output) -> subprocess.Popen:
    """``estimator_node`` as ``ros2 run`` starts it, with the whole environment ``env``, its output to ``output``.

    It runs the ``kvark_ros`` this process imported, the code replay compares it with: started in the parameter
    file's folder with that package's parent first on ``PYTHONPATH``, so that no other copy in the working
    directory (a checkout beside an installed package) is imported instead."""
    package_parent = str(Path(__file__).resolve().parents[2])
    path = os.pathsep.join(filter(None, (package_parent, env.get("PYTHONPATH"))))
    parameters = parameters.resolve()
    return subprocess.Popen([sys.executable, "-m", "kvark_ros.ros.estimator_node", "--ros-args", "--params-file",
                             str(parameters)], env={**env, "PYTHONPATH": path}, cwd=parameters.parent,
                            stdout=output, stderr=subprocess.STDOUT)


def stop_node(process: subprocess.Popen, timeout: float = 10.0) -> int:
    """SIGTERM, then SIGKILL after ``timeout`` s; the exit code (0 when the node shut down cleanly)."""
    process.terminate()
    try:
        return process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        return process.wait()


@contextmanager
def joined(ros_env: dict[str, str]):
    """This process on the domain of ``ros_env`` (``local_domain``): the variables set and rclpy initialised
    while inside; both undone on exit."""
    saved = {key: os.environ.get(key) for key in ros_env}
    os.environ.update(ros_env)
    rclpy.init(domain_id=int(ros_env["ROS_DOMAIN_ID"]))
    try:
        yield
    finally:
        rclpy.try_shutdown()
        for key, value in saved.items():
            os.environ.pop(key) if value is None else os.environ.__setitem__(key, value)


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` (s), from /proc (Linux)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _spin_until(executor: SingleThreadedExecutor, condition, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        executor.spin_once(timeout_sec=0.05)
    return True


def check_node(config_path: str, bag: str, model_dir: str | None = None, rate: float = 1.0,
               reload_at: float | None = None, domain_id: int | None = None, start_timeout: float = 120.0,
               log=print) -> dict:
    """Run the node process on ``bag`` and compare it with replay (module docstring); the figures as a dict."""
    config = load_config(config_path)
    model_dir = model_dir or config.model_dir
    recording = read_recording(bag, config.input.joint_states_topic, config.input.effort_commands_topic)
    domain = domain_id if domain_id is not None else int(np.random.default_rng().integers(*DOMAIN_RANGE))
    with tempfile.TemporaryDirectory(prefix="kvark_node_check_") as scratch:
        ros_env = local_domain(domain, Path(scratch) / "log")
        parameters = node_parameters_file(config_path, config, model_dir, Path(scratch))
        node_log = open(Path(scratch) / "node.log", "w+")
        process = start_node(parameters, {**os.environ, **ros_env}, node_log)
        figures: dict = {}
        try:
            with joined(ros_env):
                figures = _play_and_record(process, recording, rate, reload_at, start_timeout, log)
        except RuntimeError as exc:
            node_log.seek(0)
            raise RuntimeError(f"{exc}; the node's log:\n{node_log.read()[-2000:]}") from exc
        finally:
            figures["node_exit_code"] = stop_node(process)
            node_log.seek(0)
            figures["node_log_tail"] = node_log.read()[-2000:]
            node_log.close()
    figures.update(_compare(figures.pop("torque"), config, model_dir, bag))
    figures.update(config=str(config_path), bag=str(bag), model=str(model_dir), rate=rate, reload_at=reload_at,
                   domain_id=domain)
    return figures


def _play_and_record(process: subprocess.Popen, recording, rate: float, reload_at: float | None,
                     start_timeout: float, log) -> dict:
    """Wait for the node, play the recording, keep spinning until its outputs stop; the raw figures."""
    recorder, player = Recorder(NODE_NAME), BagPlayer(recording)
    executor = SingleThreadedExecutor()
    executor.add_node(recorder)
    started = time.monotonic()
    ready = _spin_until(executor, lambda: process.poll() is not None or recorder.model_ready(NODE_NAME),
                        start_timeout)
    if process.poll() is not None or not ready:
        raise RuntimeError(f"the node did not come up within {start_timeout:g} s (exit code {process.poll()})")
    player.wait_for_subscribers(10.0)
    reload = "" if reload_at is None else f", ~/reload_model at {reload_at:g} s"
    log(f"[node-check] node up in {time.monotonic() - started:.1f} s; playing {len(recording.messages)} messages, "
        f"{recording.duration:.2f} s at {rate:g}x{reload}")
    spinning = threading.Event()
    spinning.set()

    def spin() -> None:
        while spinning.is_set():
            executor.spin_once(timeout_sec=0.05)

    spinner = threading.Thread(target=spin, name="kvark_node_check_spin", daemon=True)
    spinner.start()
    reloads = [reload_at] if reload_at is not None else []

    def at(bag_time: float) -> None:
        if reloads and bag_time >= reloads[0]:
            reloads.pop()
            recorder.call_reload()

    cpu_start, wall_start = _cpu_seconds(process.pid), time.monotonic()
    late = player.play(rate, at)
    wall = time.monotonic() - wall_start
    cpu = _cpu_seconds(process.pid) - cpu_start
    count, quiet_since = -1, time.monotonic()
    while time.monotonic() - quiet_since < 1.5:          # until no estimate came for 1.5 s
        time.sleep(0.1)
        if len(recorder.torque) != count:
            count, quiet_since = len(recorder.torque), time.monotonic()
    deadline = time.monotonic() + 3.0                    # one more /diagnostics with the run's last counts
    seen = len(recorder.diagnostics)
    while len(recorder.diagnostics) <= seen and time.monotonic() < deadline:
        time.sleep(0.05)
    spinning.clear()
    spinner.join()
    sent = {stamp: player.sent_ns[k] for k, stamp in state_stamps(recording).items()}
    answered = [(stamp, published - sent[stamp]) for stamp, _, published in recorder.torque if stamp in sent]
    latency = np.array([ns for _, ns in answered]) / 1e6
    lost = _diagnostic_value(recorder.diagnostics, "input", "joint_states_lost")
    return {"torque": recorder.torque, "player_late_ms": late * 1e3, "node_cpu_cores": cpu / wall,
            "latency_ms_p50": float(np.percentile(latency, 50)) if latency.size else None,
            "latency_ms_p99": float(np.percentile(latency, 99)) if latency.size else None,
            "latency_ms_max": float(latency.max()) if latency.size else None,
            "latency_ms_max_at_s": (answered[int(latency.argmax())][0] - min(sent)) if latency.size else None,
            "node_reported_lost": None if lost is None else int(lost),
            "reload_replies": [(reply.success, reply.message) for reply in recorder.reload_replies]}


def state_stamps(recording) -> dict[int, float]:
    """Message index -> header stamp (s) of every joint state of the recording, read from its CDR bytes: a
    little-endian encapsulation header (4 bytes), then std_msgs/Header's stamp (int32 sec, uint32 nanosec)."""
    stamps = {}
    for k, (_, topic, raw) in enumerate(recording.messages):
        if topic == 0 and raw[1] == 1:                 # joint states, CDR little endian
            stamps[k] = stamp_seconds(*struct.unpack_from("<iI", raw, 4))
    return stamps


def _diagnostic_value(arrays: list[DiagnosticArray], status_name: str, key: str) -> str | None:
    for array in reversed(arrays):
        for status in array.status:
            if status.name.endswith(f": {status_name}"):
                return next((kv.value for kv in status.values if kv.key == key), None)
    return None


def _compare(torque: list, config: EstimatorConfig, model_dir: str, bag: str) -> dict:
    """The node's τ_ext against replay's on the same samples."""
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
            f"max {number('latency_ms_max')} ms (at {number('latency_ms_max_at_s')} s); node CPU {figures['node_cpu_cores']:.2f} core; the node "
            f"reported {figures['node_reported_lost']} joint states lost; on SIGTERM it exited with code "
            f"{figures['node_exit_code']}\n"
            f"[node-check] {'MATCH: the node equals replay on every sample' if passed(figures) else 'MISMATCH'}")


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser(
        "node-check", help="run the ROS 2 node on a bag over loopback DDS and compare it with replay (rclpy)",
        description="Start the estimator node as a process (as shipped, on a ROS domain of its own restricted to "
                    "this machine), play BAG into it at real time x --rate, optionally call ~/reload_model "
                    "mid-run, and compare every τ_ext it publishes with what `kvark replay` computes. Prints the "
                    "match, the latency p50/p99, the node's CPU and its exit code on SIGTERM; exit code 1 on a "
                    "mismatch or when the node does not exit with 0.")
    parser.add_argument("--config", required=True, help="estimator config YAML (the node's parameter file)")
    parser.add_argument("--model", help="model directory (default: residual_model.model_dir of the config)")
    parser.add_argument("--bag", required=True, help="bag to play (its joint states and effort commands)")
    parser.add_argument("--rate", type=playback_rate, default=1.0, help="playback speed (1 = real time, 2 = twice as fast)")
    parser.add_argument("--reload-at", type=float, metavar="SECONDS",
                        help="call ~/reload_model when the bag reaches SECONDS (the reply is not waited for)")
    parser.add_argument("--domain-id", type=int, help=f"ROS_DOMAIN_ID to use (default: drawn from "
                                                      f"{DOMAIN_RANGE[0]}-{DOMAIN_RANGE[1] - 1})")
    parser.add_argument("--json", help="also write the figures to this JSON file")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    figures = check_node(args.config, args.bag, args.model, args.rate, args.reload_at, args.domain_id)
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
