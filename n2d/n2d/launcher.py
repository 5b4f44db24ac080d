"""`n2d launch`: start the nodes of a launch description as processes, forward their logs, stop them together.

This stands in for `ros2 launch` where `launch`/`launch_ros` cannot be installed (PyPI-only ROS 2);
it reads the same YAML description as the real `launch/*.launch.py` files. All nodes stop when
the user presses Ctrl-C, when `stop()` is called, or as soon as one of them exits.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable

from n2d.launch_description import LaunchSpec, resolve_arguments, substitute
from n2d_common.process import die_with_parent
from n2d_common.ros import ros_environment


def _param_arg(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        # rcl parses -p values as YAML: quote strings so "1.0" or "on" stay strings.
        return "'" + value.replace("'", "''") + "'"
    return str(value)


def node_command(node, args: dict[str, str]) -> list[str]:
    """The command line that starts `node` (a NodeSpec) with its resolved parameters."""
    cmd = [sys.executable, "-m", node.module, "--ros-args", "-r", f"__node:={node.name}",
           "-r", f"__ns:={node.namespace}"]
    for key, value in node.parameters.items():
        cmd += ["-p", f"{key}:={_param_arg(substitute(value, args))}"]
    return cmd


class Launch:
    """A running launch description. Use as a context manager, or `start()` ... `stop()`."""

    def __init__(self, spec: LaunchSpec, arguments: dict[str, str] | None = None, *,
                 env: dict | None = None, log: Callable[[str], None] | None = None):
        self.spec = spec
        self.args = resolve_arguments(spec, arguments or {})
        self.env = ros_environment(env=dict(os.environ if env is None else env))
        self.env.setdefault("PYTHONUNBUFFERED", "1")
        self.log = log or (lambda line: print(line, file=sys.stderr, flush=True))
        self.procs: dict[str, subprocess.Popen] = {}
        self._threads: list[threading.Thread] = []

    def start(self) -> Launch:
        for node in (n for n in self.spec.nodes if n.enabled(self.args)):
            proc = subprocess.Popen(node_command(node, self.args), env=self.env, stdout=subprocess.PIPE,
                                    stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, text=True, bufsize=1,
                                    start_new_session=True, preexec_fn=die_with_parent)
            self.procs[node.name] = proc
            t = threading.Thread(target=self._forward, args=(node.name, proc), daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def _forward(self, name: str, proc: subprocess.Popen) -> None:
        for line in proc.stdout:
            self.log(f"[{name}] {line.rstrip()}")

    def dead(self) -> list[tuple[str, int]]:
        """(name, exit code) of the nodes that have exited."""
        return [(n, p.returncode) for n, p in self.procs.items() if p.poll() is not None]

    def wait(self, poll_s: float = 0.2) -> int:
        """Block until a node exits (or Ctrl-C, or SIGTERM); stop the others and return the first non-zero exit code."""
        def terminate(_sig, _frame):
            raise KeyboardInterrupt

        main = threading.current_thread() is threading.main_thread()
        previous = signal.signal(signal.SIGTERM, terminate) if main else None
        try:
            while not self.dead():
                time.sleep(poll_s)
            for name, code in self.dead():
                self.log(f"[launch] {name} exited with code {code}: stopping the others")
        except KeyboardInterrupt:
            self.log("[launch] Ctrl-C: stopping all nodes")
        finally:
            if main:
                signal.signal(signal.SIGTERM, previous)
            self.stop()
        codes = [c for _, c in self.dead() if c not in (0, -signal.SIGINT, -signal.SIGTERM)]
        return codes[0] if codes else 0

    def stop(self, timeout_s: float = 10.0) -> None:
        """SIGINT every node, then SIGTERM, then SIGKILL whatever is still alive."""
        for sig, grace in ((signal.SIGINT, timeout_s), (signal.SIGTERM, 3.0), (signal.SIGKILL, 3.0)):
            alive = [p for p in self.procs.values() if p.poll() is None]
            if not alive:
                break
            for p in alive:
                try:
                    os.killpg(p.pid, sig)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + grace
            for p in alive:
                try:
                    p.wait(max(0.0, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    pass
        for t in self._threads:
            t.join(timeout=1.0)

    def __enter__(self) -> Launch:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
