"""The `n2d` command: one entry point, a subcommand per job. Each is a thin shell over a library function.

Errors a user can fix print as one line plus a hint and exit with code 2; Ctrl-C exits with 130
and keeps finished work, so the same command resumes.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from n2d_common import __version__
from n2d_common.errors import N2DError


def _progress_bar(desc: str):
    """A ProgressFn drawing one tqdm bar (0..100 %) with the stage and message as postfix.

    The bar appears with the first report, so a job that fails its input checks prints only its error."""
    from tqdm import tqdm

    bar = None

    def report(p) -> None:
        nonlocal bar
        if bar is None:
            bar = tqdm(total=100, desc=desc, unit="%", dynamic_ncols=True,
                       bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}<{remaining} {postfix}")
        bar.n = round(100 * min(max(p.fraction, 0.0), 1.0))
        bar.set_postfix_str(f"{p.stage} {p.message}".strip(), refresh=False)
        bar.refresh()
        if p.fraction >= 1.0:
            bar.close()

    return report


def _config(cls, args):
    from n2d_common.config import load_config

    return load_config(cls, args.config, args.set)


def _add_config_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=Path, help="YAML/JSON file with config values")
    p.add_argument("-s", "--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override one config value, e.g. --set views=24 (repeatable)")


def cmd_demo(args) -> int:
    from n2d.demo import DemoConfig, run_demo

    cfg = _config(DemoConfig, args)
    summary = run_demo(args.out, cfg, overwrite=args.overwrite, progress=_progress_bar("demo"))
    print(f"demo: {summary['views']} views in {summary['seconds']} s; driver vs simulator ground truth: "
          f"max {summary['max_driver_vs_truth_deg']:.4f} deg")
    print(f"demo: wrote {args.out}/ (contact_sheet.png, frames/, frames.json)")
    return 0


def _launch(name: str, pairs: list[str]) -> int:
    from n2d.launch_description import load
    from n2d.launcher import Launch

    given = {}
    for pair in pairs:
        key, sep, value = pair.partition(":=")
        if not sep:
            raise N2DError(f"launch argument {pair!r} is not of the form name:=value", "e.g. object:=bottle")
        given[key] = value
    spec = load(name)
    launch = Launch(spec, given).start()
    print(f"n2d launch {spec.name}: started {', '.join(launch.procs)} (Ctrl-C stops them)", file=sys.stderr)
    return launch.wait()


def cmd_launch(args) -> int:
    if args.name is None:
        from n2d.launch_description import available, load

        for name in available():
            spec = load(name)
            print(f"{name}: {spec.description}")
            for arg, a in spec.arguments.items():
                print(f"    {arg}:={a.default}  {a.description}")
        return 0
    return _launch(args.name, args.arguments)


def cmd_sim(args) -> int:
    pairs = [f"object:={args.object}", f"port:={args.port}"] + args.arguments
    return _launch("sim", pairs)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="n2d", description="n2d: from an object on a turntable to a live 6D pose estimator (ROS 2).",
        epilog="Run 'n2d COMMAND --help' for the options of a command.")
    parser.add_argument("--version", action="version", version=f"n2d {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("demo", help="run the whole job on the embedded simulated world (no hardware)",
                       description="Bring up the simulated turntable world (Dynamixel servo emulated on a pty + "
                       "rendered camera), sweep the plate through the real driver, and write a run directory "
                       "with the frames and a contact sheet. Re-running a finished demo does nothing unless "
                       "--overwrite.")
    p.add_argument("out", nargs="?", type=Path, default=Path("n2d_runs/demo"),
                   help="run directory (default: n2d_runs/demo)")
    p.add_argument("--overwrite", action="store_true", help="replace a finished run (only once the new one is done)")
    _add_config_options(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("sim", help="start the simulated world until Ctrl-C",
                       description="Start the simulated servo (on a pty at --port) and the simulated camera "
                       "(topics under /n2d). Point the turntable driver at --port.")
    p.add_argument("--object", default="box", help="sample object (box, bottle) or a model directory")
    p.add_argument("--port", default="/tmp/n2d_sim/ttyDXL", help="where the emulated servo's serial port appears")
    p.add_argument("arguments", nargs="*", metavar="NAME:=VALUE", help="further launch arguments (see n2d launch)")
    p.set_defaults(func=cmd_sim)

    p = sub.add_parser("launch", help="start the nodes of a launch description (like ros2 launch)",
                       description="Start the nodes listed in launch/NAME.yaml (the same list launch/NAME.launch.py "
                       "gives ros2 launch) as processes, forward their logs, and stop them all on Ctrl-C or "
                       "when one exits. Without NAME: list the descriptions and their arguments.")
    p.add_argument("name", nargs="?", help="launch description, e.g. sim")
    p.add_argument("arguments", nargs="*", metavar="NAME:=VALUE", help="launch arguments")
    p.set_defaults(func=cmd_launch)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except N2DError as exc:
        print(f"n2d: error: {exc.message}", file=sys.stderr)
        if exc.hint:
            print(f"  hint: {exc.hint}", file=sys.stderr)
        return 2
    except OSError as exc:
        where = f": {exc.filename}" if exc.filename else ""
        print(f"n2d: error: {exc.strerror or exc}{where}", file=sys.stderr)
        print("  hint: check free disk space and permissions; finished work is kept", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("n2d: interrupted; finished work is kept and the same command resumes it", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
