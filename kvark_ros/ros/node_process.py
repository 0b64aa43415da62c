"""The node as a process of its own, and what it and the machine cost while ``kvark node-check`` plays a bag.

Starting and stopping ``estimator_node`` as ``ros2 run`` does, on a ROS domain restricted to this machine; a
process's CPU time and the machine's busy cores from ``/proc`` (Linux), so that every figure comes with the load
present; processes that keep other cores busy (``--load-cores``: a robot computer always runs something else);
and callgrind's instruction count of the node (``--callgrind``), which the other processes on the machine do
not change.

The ROS 2 wheels' ``ros_wheels_bootstrapper.pth`` re-executes every Python start in the environment once, to set
``LD_LIBRARY_PATH``; a process started from one that already ran (as the node is here) inherits the variable and
is not re-executed, and a profiler must follow the exec (callgrind: ``--trace-children=yes``).
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Iterator

import rclpy

SPIN = "while True: pass"          # a busy process: one core's worth of load
SETTLE = 1.0                       # s the busy processes run before the measurement: past their start-up
__all__ = ["Callgrind", "Usage", "cpu_seconds", "joined", "local_domain", "spinning", "start_node", "stop_node"]


def local_domain(domain: int, log_dir: Path) -> dict[str, str]:
    """The variables that put a ROS 2 process on domain ``domain``, on this machine only, logging to ``log_dir``."""
    return {"ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_LOG_DIR": str(log_dir)}


def start_node(parameters: Path, env: dict[str, str], output: IO, prefix: tuple[str, ...] = (),
               ros_arguments: tuple[str, ...] = (), cwd: Path | None = None) -> subprocess.Popen:
    """``estimator_node`` as ``ros2 run`` starts it, with the whole environment ``env``, its output to ``output``
    (``prefix``: a command to run it under, e.g. valgrind; ``ros_arguments``: more after ``--ros-args``, e.g.
    ``-r __ns:=/lbr``), in ``cwd`` (default: the parameter file's folder).

    It runs the ``kvark_ros`` this process imported, the code replay compares it with: with that package's parent
    first on ``PYTHONPATH``, so that no other copy in the working directory (a checkout beside an installed package)
    is imported instead."""
    package_parent = str(Path(__file__).resolve().parents[2])
    path = os.pathsep.join(filter(None, (package_parent, env.get("PYTHONPATH"))))
    parameters = parameters.resolve()
    return subprocess.Popen([*prefix, sys.executable, "-m", "kvark_ros.ros.estimator_node", "--ros-args",
                             *ros_arguments, "--params-file", str(parameters)], env={**env, "PYTHONPATH": path},
                            cwd=cwd or parameters.parent, stdout=output, stderr=subprocess.STDOUT)


def stop_node(process: subprocess.Popen, timeout: float = 10.0) -> int:
    """SIGTERM, then SIGKILL after ``timeout`` s; the exit code (0 when the node shut down cleanly)."""
    process.terminate()
    try:
        return process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        return process.wait()


@contextmanager
def joined(ros_env: dict[str, str]) -> Iterator[None]:
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


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` (s), from /proc (Linux)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _process_seconds() -> dict[int, float]:
    """pid -> CPU time (s) of every process on the machine. Summed, these are exact where /proc/stat's per-core
    ticks are not: with a tick-less idle kernel a process that runs for a fraction of a millisecond at each wake
    is rarely running when a tick samples the core."""
    seconds = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                seconds[int(entry.name)] = cpu_seconds(int(entry.name))
            except (OSError, IndexError, ValueError):    # a process that ended meanwhile
                continue
    return seconds


def _used(before: dict[int, float], after: dict[int, float]) -> float:
    """CPU time (s) the processes present at both marks used in between."""
    return sum(after[pid] - before[pid] for pid in before.keys() & after.keys())


@dataclass
class Usage:
    """CPU used between ``start`` and ``stop``, in cores (CPU seconds per second): the node's, this process's and
    the whole machine's (every process that ran through the interval)."""

    node_pid: int
    node: float = 0.0
    checker: float = 0.0
    machine: float = 0.0

    def start(self) -> None:
        self._processes = _process_seconds()
        self._started = time.monotonic()

    def stop(self) -> None:
        wall = time.monotonic() - self._started
        processes = _process_seconds()
        self.node = (processes[self.node_pid] - self._processes[self.node_pid]) / wall
        self.checker = (processes[os.getpid()] - self._processes[os.getpid()]) / wall
        self.machine = _used(self._processes, processes) / wall


@contextmanager
def spinning(count: int) -> Iterator[list[subprocess.Popen]]:
    """``count`` busy Python processes while inside (each keeps one core busy), ``SETTLE`` s old on entry: their
    start-up (an interpreter or two each) is not part of what they load; stopped on exit."""
    processes = [subprocess.Popen([sys.executable, "-c", SPIN]) for _ in range(count)]
    if processes:
        time.sleep(SETTLE)
    try:
        yield processes
    finally:
        for process in processes:
            process.kill()
            process.wait()


class Callgrind:
    """The node under valgrind's callgrind, its instructions counted only when asked (``--instr-atstart=no``):
    ``measure`` counts them over a stretch of work, then over as long a stretch of idling, into ``folder``."""

    def __init__(self, folder: Path) -> None:
        if shutil.which("valgrind") is None or shutil.which("callgrind_control") is None:
            raise RuntimeError("--callgrind needs valgrind (callgrind_control) on PATH")
        self.folder = folder
        self.prefix = ("valgrind", "--tool=callgrind", "--trace-children=yes", "--instr-atstart=no",
                       f"--callgrind-out-file={folder / 'callgrind.out.%p'}")

    @staticmethod
    def _control(pid: int, *arguments: str) -> None:
        subprocess.run(["callgrind_control", *arguments, str(pid)], check=True, capture_output=True)

    def start(self, pid: int) -> None:
        self._control(pid, "--instr=on")
        self._started = time.monotonic()

    def instructions(self, pid: int, idle: float) -> tuple[float, float]:
        """Dump what was counted since ``start``, count ``idle`` s of idling and dump it: (the instructions since
        ``start`` less the idle rate over that time, the idle instructions per second)."""
        self._control(pid, "--dump")
        seconds = time.monotonic() - self._started
        time.sleep(idle)
        self._control(pid, "--dump")
        self._control(pid, "--instr=off")
        parts = sorted(self.folder.glob(f"callgrind.out.{pid}.*"), key=lambda path: int(path.suffix[1:]))
        work, rest = (self._total(path) for path in parts[-2:])
        return work - rest / idle * seconds, rest / idle

    @staticmethod
    def _total(path: Path) -> int:
        return next(int(line.split()[1]) for line in path.read_text().splitlines() if line.startswith("totals:"))
