"""Declarative launch descriptions: one YAML per launch file, read by `n2d launch` and by `*.launch.py`.

A description names its arguments (with defaults and descriptions) and its nodes (package,
executable, name, namespace, parameters). Parameter values may contain `${arg}` references.
Executables follow one convention: `<package>.nodes.<executable>:main`, so `n2d launch` can start
them with `python -m` where `ros2 launch` starts the installed console scripts.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from n2d_common.config import read_mapping
from n2d_common.errors import ConfigError

_REF = re.compile(r"\$\{(\w+)\}")


@dataclass
class ArgumentSpec:
    """A launch argument."""

    default: str
    """Value used when the caller gives none."""
    description: str = ""
    """What the argument sets."""


@dataclass
class NodeSpec:
    """One node of a launch description."""

    package: str
    """ROS package that holds the node."""
    executable: str
    """Console script (and module `<package>.nodes.<executable>`)."""
    name: str
    """Node name."""
    namespace: str = "/n2d"
    """Node namespace."""
    parameters: dict = field(default_factory=dict)
    """Parameter name -> value; string values may contain `${argument}`."""
    condition: str = ""
    """Start the node only when this (e.g. `${sim}`) is true; empty: always."""

    def enabled(self, args: dict[str, str]) -> bool:
        if not self.condition:
            return True
        value = substitute(self.condition, args)
        return value is True or str(value).lower() in ("true", "1", "yes", "on")

    @property
    def module(self) -> str:
        return f"{self.package}.nodes.{self.executable}"


@dataclass
class LaunchSpec:
    """A launch description: its arguments and nodes."""

    name: str
    description: str
    arguments: dict[str, ArgumentSpec]
    nodes: list[NodeSpec]


def launch_dir() -> Path:
    """The directory holding the launch files: share/n2d/launch when installed, else the source tree's."""
    try:
        from ament_index_python.packages import get_package_share_directory

        installed = Path(get_package_share_directory("n2d")) / "launch"
        if installed.is_dir():
            return installed
    except (ImportError, LookupError, OSError, ValueError):
        pass
    return Path(__file__).resolve().parent.parent / "launch"


def available() -> list[str]:
    """Names of the launch descriptions that ship with n2d."""
    return sorted(p.stem for p in launch_dir().glob("*.yaml"))


def load(name_or_path: str | Path) -> LaunchSpec:
    """Read a launch description by name (e.g. "sim") or from a YAML path."""
    path = Path(name_or_path)
    if path.suffix not in (".yaml", ".yml"):
        path = launch_dir() / f"{name_or_path}.yaml"
        if not path.is_file():
            raise ConfigError(f"no launch description named {name_or_path!r}",
                              f"available: {', '.join(available())}")
    data = read_mapping(path)
    try:
        arguments = {k: ArgumentSpec(str(v.get("default", "")), v.get("description", ""))
                     for k, v in (data.get("arguments") or {}).items()}
        nodes = [NodeSpec(**n) for n in data["nodes"]]
    except (KeyError, TypeError, AttributeError) as exc:
        raise ConfigError(f"launch description {path} is malformed: {exc}") from None
    return LaunchSpec(path.stem, data.get("description", ""), arguments, nodes)


def resolve_arguments(spec: LaunchSpec, given: dict[str, str]) -> dict[str, str]:
    """Defaults overridden by `given`; unknown argument names raise ConfigError."""
    unknown = sorted(set(given) - set(spec.arguments))
    if unknown:
        raise ConfigError(f"launch {spec.name}: unknown argument(s) {', '.join(unknown)}",
                          f"arguments: {', '.join(f'{k}:=<{v.default}>' for k, v in spec.arguments.items())}")
    return {k: given.get(k, a.default) for k, a in spec.arguments.items()}


def substitute(value: object, args: dict[str, str]) -> object:
    """Replace `${name}` references by argument values. As in launch_ros, a string that held a
    reference is then read as a YAML scalar, so `${samples}` with samples:=8 becomes the integer 8."""
    if not isinstance(value, str) or not _REF.search(value):
        return value

    def ref(m: re.Match) -> str:
        if m.group(1) not in args:
            raise ConfigError(f"launch parameter refers to unknown argument ${{{m.group(1)}}}")
        return args[m.group(1)]

    text = _REF.sub(ref, value)
    try:
        typed = yaml.safe_load(text)
    except yaml.YAMLError:
        return text
    return typed if isinstance(typed, (bool, int, float, str)) else text


def ros_launch_description(path: str | Path):
    """A `launch.LaunchDescription` of the YAML at `path`, for `ros2 launch` on a machine with ROS installed."""
    from launch.actions import DeclareLaunchArgument
    from launch.conditions import IfCondition
    from launch.substitutions import LaunchConfiguration, TextSubstitution
    from launch_ros.actions import Node

    from launch import LaunchDescription

    spec = load(Path(path))

    def subs(value: object) -> object:
        if not isinstance(value, str) or not _REF.search(value):
            return value
        parts, pos = [], 0
        for m in _REF.finditer(value):
            if m.start() > pos:
                parts.append(TextSubstitution(text=value[pos:m.start()]))
            parts.append(LaunchConfiguration(m.group(1)))
            pos = m.end()
        if pos < len(value):
            parts.append(TextSubstitution(text=value[pos:]))
        return parts

    actions = [DeclareLaunchArgument(k, default_value=a.default, description=a.description)
               for k, a in spec.arguments.items()]
    actions += [Node(package=n.package, executable=n.executable, name=n.name, namespace=n.namespace,
                     parameters=[{k: subs(v) for k, v in n.parameters.items()}], output="screen", emulate_tty=True,
                     condition=IfCondition(subs(n.condition)) if n.condition else None)
                for n in spec.nodes]
    return LaunchDescription(actions)
