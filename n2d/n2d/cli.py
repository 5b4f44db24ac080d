"""The `n2d` command: one entry point, a subcommand per job. Each is a thin shell over a library function.

Errors a user can fix print as one line plus a hint and exit with code 2; Ctrl-C exits with 130
and keeps finished work, so the same command resumes.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path

from n2d_common import __version__
from n2d_common.errors import ConfigError, N2DError


def _close_progress_bars() -> None:
    """End the progress bars still drawn (a job that failed half way), so the error starts a line of its own."""
    from tqdm import tqdm

    for bar in list(getattr(tqdm, "_instances", ())):
        bar.close()


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


def _config(cls, args, base=None):
    from n2d_common.config import load_config

    return load_config(cls, args.config, args.set, base=base)


def _add_config_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=Path, help="YAML/JSON file with config values")
    p.add_argument("-s", "--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override one config value, e.g. --set views=24 (repeatable)")


def cmd_demo(args) -> int:
    from n2d.demo import DemoConfig, run_demo

    cfg = _config(DemoConfig, args)
    s = run_demo(args.out, cfg, overwrite=args.overwrite, progress=_progress_bar("demo"))
    print(f"demo: {s['object']} in {s['seconds_total'] / 60:.1f} min; per stage: "
          + ", ".join(f"{stage} {seconds:.0f} s" for stage, seconds in s["seconds"].items()))
    for placed in (s.get("placements") or {}).get("registered", []):
        print(f"demo: placement {placed['placement'] + 1} registered to the first (turned {placed['turned_deg']:.1f} "
              f"deg, views covered {100 * placed['min_view_coverage']:.1f} %) and fused: a closed model")
    for test, by_precision in s["evaluation"].items():
        for precision, r in by_precision.items():
            print(f"demo: {test} test set ({precision}): {_accuracy_line(r)}")
    if s["live"]:
        print(f"demo: live dope_node vs the simulator's ground truth ({s['live']['precision']}): "
              f"{_accuracy_line(s['live'])}")
    print(f"demo: wrote {s['run_dir']}/ (capture/, model/, dataset/, dope/, live/, run.json, demo.json)")
    return 0


def _accuracy_line(r: dict) -> str:
    median = r.get("adds_median_mm")
    return (f"ADD-S {100 * r['adds_accuracy_10pct']:.1f} %, ADD {100 * r['add_accuracy_10pct']:.1f} % at 10 % of the "
            f"{r['diameter_mm']:.0f} mm diameter; {r['detected']}/{r['instances']} found, median ADD-S "
            + ("-" if median is None else f"{median:.1f} mm"))


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


def cmd_board(args) -> int:
    from n2d_capture.board_print import write_board_print
    from n2d_common.formats.board import BoardSpec

    spec = _config(BoardSpec, args)
    paths = write_board_print(spec, args.out, dpi=args.dpi)
    w, h = spec.sheet_m
    print(f"board: {spec.squares_x}x{spec.squares_y} squares of {spec.square_m * 1000:g} mm on a "
          f"{w * 1000:.0f} x {h * 1000:.0f} mm sheet; print {paths['pdf']} at 100 % (actual size)")
    print(f"board: spec in {paths['json']}, image in {paths['png']}")
    return 0


def _capture_io(args, cancel, stack):
    """(rotator, camera) for `n2d capture` from its --port / --rotate-action / --camera options; what they
    hold open is closed by the ExitStack `stack`."""
    from n2d_capture.turntable import Turntable, TurntableConfig
    from n2d_common.ros import background_node

    kind, _, where = args.camera.partition(":")
    if kind not in ("ros", "cv") or (kind == "cv" and not where):
        raise N2DError(f"unknown camera {args.camera!r}", "use ros[:IMAGE_TOPIC] or cv:DEVICE_OR_FILE")
    node = background_node("n2d_capture_cli") if kind == "ros" or args.rotate_action else None
    node = stack.enter_context(node) if node is not None else None
    if kind == "cv":
        from n2d_capture.camera_sources import OpenCVSource

        camera = OpenCVSource(where)
        stack.callback(camera.close)
    else:
        from n2d_capture.nodes.ros_io import RosFrameSource

        topic = where or "/n2d/camera/image_raw"
        camera = RosFrameSource(node, topic, topic.rsplit("/", 1)[0] + "/camera_info")
    if args.rotate_action:
        from n2d_capture.nodes.ros_io import RosRotator

        return RosRotator(node, args.rotate_action, cancel), camera
    return stack.enter_context(Turntable(TurntableConfig(port=args.port, baud=args.baud,
                                                         servo_id=args.servo_id))), camera


def _capture_config(args):
    """CaptureConfig from --config / --set, with the board spec of --board (board.json of `n2d board`)."""
    from n2d_capture.capture import CaptureConfig
    from n2d_common.config import read_mapping
    from n2d_common.formats.board import BoardSpec

    cfg = _config(CaptureConfig, args)
    if args.board:
        cfg.board = BoardSpec.from_dict(read_mapping(args.board))
    return cfg


def _posed_counts(summary: dict) -> str:
    counts = [(summary.get(f"posed_from_{k}", 0), what) for k, what in (
        ("axis", "from the fitted axis"), ("board", "from their board pose"), ("colmap", "by COLMAP"),
        ("servo", "from the servo angle alone"))]
    return ", ".join(f"{n} {what}" for n, what in counts if n)


def _wait_for_enter(placement: int, placements: int) -> None:
    """`n2d capture --set placements=2`: the person at the turntable turns the object over and presses Enter."""
    from n2d_capture.capture import turn_over_request

    input(f"\ncapture: {turn_over_request(placement, placements).message}: press Enter when it lies so ")


def cmd_capture(args) -> int:
    import threading

    from n2d_capture.capture import capture

    cfg = _capture_config(args)
    if args.views:
        cfg.sweep.views = args.views
    cancel = threading.Event()
    with contextlib.ExitStack() as stack:
        rotator, camera = _capture_io(args, cancel, stack)
        try:
            summary = capture(args.session, cfg, rotator, camera, empty_plate=args.empty,
                              overwrite=args.overwrite, progress=_progress_bar("capture"), cancel=cancel,
                              turn_over=lambda placement: _wait_for_enter(placement, cfg.placements))
        except KeyboardInterrupt:
            cancel.set()
            raise
    if not summary["complete"]:
        print(f"capture: {summary['views']} empty-plate views kept; {summary['message']}")
        return 0
    print(f"capture: {summary['views']} views (posed {_posed_counts(summary)}); turntable fit residual "
          f"{summary['fit_rotation_residual_deg']:.3f} deg / {summary['fit_translation_residual_mm']:.2f} mm")
    print(f"capture: wrote {args.session}/ (transforms.json, capture.json, contact_sheet.png)")
    return 0


def cmd_capture_import(args) -> int:
    from n2d_capture.importer import import_photos

    # posed.KEY=VALUE sets PosedImportConfig (--from nerfstudio|colmap), every other key the CaptureConfig
    posed = [s.removeprefix("posed.") for s in args.set if s.startswith("posed.")]
    args.set = [s for s in args.set if not s.startswith("posed.")]
    cfg = _capture_config(args)
    if args.source != "photos":
        return _import_posed(args, cfg, posed)
    if args.scale_from or posed:
        raise ConfigError("--scale-from and posed.* settings need --from nerfstudio or --from colmap",
                          "photos are made metric by the board; drop them")
    summary = import_photos(args.photos, args.out, cfg, empty_dir=args.empty, intrinsics=args.intrinsics,
                            overwrite=args.overwrite, progress=_progress_bar("import"))
    print(f"import: {summary['views']} views (posed {_posed_counts(summary)}); "
          f"wrote {args.out}/ (transforms.json, capture.json, contact_sheet.png)")
    return 0


def _import_posed(args, cfg, posed: list[str]) -> int:
    from dataclasses import replace

    from n2d_capture.posed_import import PosedImportConfig, import_posed
    from n2d_common.config import load_config

    if args.empty or args.intrinsics:
        raise ConfigError(f"--empty and --intrinsics are for photos; a {args.source} source brings its own camera",
                          "drop them, or import the photos without --from")
    posed_cfg = load_config(PosedImportConfig, None, posed)
    posed_cfg = replace(posed_cfg, capture=cfg, scale_from=args.scale_from or posed_cfg.scale_from)
    summary = import_posed(args.photos, args.out, posed_cfg, source=args.source, overwrite=args.overwrite,
                           progress=_progress_bar("import"))
    scale = (f"metric from the board ({summary['alignment_mm']:.2f} mm RMS)" if summary["scale_from"] == "board"
             else "metric from --scale-from")
    print(f"import: {summary['views']} {args.source} views, {scale}; camera ring residual "
          f"{summary['ring_residual_mm']:.2f} mm; masks {summary['masks_given']} given, {summary['masks_made']} made; "
          f"wrote {args.out}/ (transforms.json, capture.json, contact_sheet.png)")
    return 0


def cmd_reconstruct(args) -> int:
    import threading

    from n2d_reconstruct.neus import NeusConfig
    from n2d_reconstruct.pipeline import ReconstructConfig, reconstruct

    # The preset is the base that --config and --set refine.
    cfg = _config(ReconstructConfig, args, base=ReconstructConfig(neus=NeusConfig.preset(args.neus_preset)))
    if args.method:
        cfg.method = args.method
    if args.name:
        cfg.object_name = args.name
    cancel = threading.Event()
    try:
        report = reconstruct(args.session, args.out, cfg, ground_truth=args.ground_truth, overwrite=args.overwrite,
                             progress=_progress_bar("reconstruct"), cancel=cancel)
    except KeyboardInterrupt:
        cancel.set()
        raise
    model, held = report["model"], report.get("heldout")
    print(f"reconstruct: {model['faces']} faces, size {' x '.join(f'{x:.1f}' for x in model['size_mm'])} mm, "
          f"{report['timings_s']['total']:.0f} s")
    if held:
        print(f"reconstruct: held-out textured mesh PSNR {held['mesh_psnr_db']:.2f} dB, SSIM {held['mesh_ssim']:.4f}")
        if "field_psnr_db" in held:
            print(f"reconstruct: held-out radiance field PSNR {held['field_psnr_db']:.2f} dB, "
                  f"SSIM {held['field_ssim']:.4f}")
    if "geometry" in report:
        g = report["geometry"]
        print(f"reconstruct: Chamfer {g['chamfer_mm']:.3f} mm ({g['chamfer_pct_diameter']:.2f} % of the diameter), "
              f"F-score {g['fscore']:.3f} at {g['fscore_threshold_mm']:g} mm")
    print(f"reconstruct: wrote {args.out}/ (mesh.obj, mesh.glb, models_info.json, report.json, preview.png)")
    return 0


def _rgb(text: str) -> tuple[int, int, int]:
    """R,G,B (0..255) of --colour."""
    parts = text.replace(" ", "").split(",")
    if len(parts) != 3 or not all(p.isdigit() and int(p) <= 255 for p in parts):
        raise argparse.ArgumentTypeError(f"{text!r} is not R,G,B with each in 0..255 (e.g. 200,30,30)")
    return tuple(int(p) for p in parts)


def cmd_model_import(args) -> int:
    import re

    from n2d_reconstruct.model_import import ImportConfig, import_model

    cfg = _config(ImportConfig, args)
    for name, value in (("units", args.units), ("up", args.up), ("colour_rgb", args.colour),
                        ("symmetry", args.symmetry)):
        if value is not None:
            setattr(cfg, name, value)
    cfg.object_name = args.name or (re.sub(r"[^A-Za-z0-9_-]", "_", args.mesh.stem).strip("_-") or "object")
    cfg.__post_init__()
    s = import_model(args.mesh, args.out, cfg, overwrite=args.overwrite, progress=_progress_bar("import"))
    src, model, sym = s["source"], s["model"], s["symmetry"]
    print(f"model import: units {src['units']} ({src['units_reason']}); up axis {src['up']}; {src['appearance']}")
    symmetric = ("none" if sym["group_order"] == 1 else "continuous" if sym["group_order"] is None
                 else f"{sym['group_order']:g}-fold")
    faces = f"{model['faces']} faces" + (f" (decimated from {src['faces']})" if src["decimated"] else "")
    print(f"model import: {faces}, size {' x '.join(f'{x:.1f}' for x in model['size_mm'])} mm, "
          f"symmetry {symmetric if sym['mode'] == 'auto' else 'not detected (--symmetry none)'}")
    print(f"model import: wrote {args.out}/ (mesh.obj, mesh.glb, models_info.json; n2d.json has T_source_object)")
    return 0


def cmd_dataset(args) -> int:
    import threading

    from n2d_dataset.config import DatasetConfig
    from n2d_dataset.generate import generate_dataset

    cfg = _config(DatasetConfig, args)
    for name in ("frames", "workers", "seed"):
        if getattr(args, name) is not None:
            setattr(cfg, name, getattr(args, name))
    cfg.__post_init__()
    cancel = threading.Event()
    try:
        summary = generate_dataset(args.models, args.out, cfg, overwrite=args.overwrite,
                                   progress=_progress_bar("dataset"), cancel=cancel, cluster=args.cluster)
    except KeyboardInterrupt:
        cancel.set()
        raise
    rate = summary["frames"] - summary["resumed_frames"]
    print(f"dataset: {summary['frames']} frames, {summary['instances']} annotated instances "
          f"({rate} rendered in {summary['wall_s']:.0f} s)")
    print(f"dataset: wrote {args.out}/ (train_pbr/ BOP chunks with DOPE JSON beside each image, models/, "
          "camera.json, contact_sheet.png)")
    return 0


def cmd_train(args) -> int:
    import threading

    from n2d_dope.config import TIMED_EPOCHS, TrainConfig
    from n2d_dope.train import train

    cfg = _config(TrainConfig, args, base=TrainConfig.preset(args.backbone))
    if args.epochs:
        cfg.epochs = args.epochs
    if args.minutes is not None:
        cfg.max_minutes = args.minutes
        cfg.epochs = args.epochs or TIMED_EPOCHS
    if args.init:
        cfg.init_model = str(args.init.absolute())
    cfg.__post_init__()
    cancel = threading.Event()
    try:
        s = train(args.dataset, args.out, cfg, object_name=args.object, overwrite=args.overwrite,
                  progress=_progress_bar("train"), cancel=cancel, ddp=args.ddp)
    except KeyboardInterrupt:
        cancel.set()
        raise
    if s is None:  # a rank other than 0 of a torchrun launch: rank 0 reports
        return 0
    held = f", held-out loss {s['held_out_loss']:.5f}" if s["held_out_loss"] is not None else ""
    print(f"train: {s['object']} ({s['backbone']}, {s['parameters'] / 1e6:.2f} M parameters): {s['steps']} steps on "
          f"{s['train_frames']} frames in {s['train_seconds']:.0f} s on {s['device']}{held}")
    export = s["export"]
    line = f"ONNX opset {export['opset']}, max |onnx - torch| {export['max_abs_diff_vs_torch']:.1e}"
    if "int8" in export:
        line += f"; INT8 belief max |int8 - fp32| {export['int8']['belief_max_abs_diff_vs_fp32']:.3f}"
    print(f"train: {line}")
    print(f"train: wrote {args.out}/ (model.onnx, config.json, checkpoint.pt, training.json)")
    return 0


def cmd_pipeline(args) -> int:
    import threading

    from n2d.objects import parse_objects, run_objects
    from n2d.pipeline import PipelineConfig

    cfg = _config(PipelineConfig, args)
    objects = parse_objects(args.objects)
    stages = [s.strip() for s in args.stages.split(",")] if args.stages else None
    bars: dict = {}
    cancel = threading.Event()
    try:
        results = run_objects(args.run_dir, objects, cfg, stages=stages, cluster=args.cluster, cancel=cancel,
                              progress_for=lambda name: bars.setdefault(name, _progress_bar(name)))
    except KeyboardInterrupt:
        cancel.set()
        raise
    _close_progress_bars()
    for r in results:
        if r["ok"]:
            print(f"pipeline: {r['name']}: {', '.join(r['done']) or 'nothing'} done, in {r['run_dir']}/")
        else:
            print(f"pipeline: {r['name']}: failed: {r['error']}", file=sys.stderr)
            print(f"  hint: {r['hint']}", file=sys.stderr)
    failed = [r["name"] for r in results if not r["ok"]]
    print(f"pipeline: {len(results) - len(failed)} of {len(results)} objects finished"
          + (f"; failed: {', '.join(failed)} (fix it, then the same command resumes every object)" if failed else ""))
    return 2 if failed else 0


def cmd_evaluate(args) -> int:
    from n2d_common.contracts import read_manifest
    from n2d_dope.config import RefineConfig
    from n2d_dope.evaluate import evaluate, evaluate_session

    test = read_manifest(args.test) if args.test.is_dir() else None
    refine = RefineConfig() if args.refine else None
    if args.object_id is not None:
        from n2d_dope.bop_eval import evaluate_bop

        name = args.name or f"bop_{args.split}"
        r = evaluate_bop(args.model, args.test, args.object_id, split=args.split, targets=args.targets, name=name,
                         precision=args.precision, refine=refine, max_images=args.frames,
                         progress=_progress_bar("evaluate"))
        print(f"evaluate: BOP MSSD / MSPD recall {r['mssd_recall']:.3f} / {r['mspd_recall']:.3f}; ADD-S by "
              "visible fraction: " + ", ".join(f"{k} {100 * v['adds_accuracy_10pct']:.1f} % ({v['instances']})"
                                               for k, v in r["visibility_buckets"].items() if v["instances"]))
        print(f"evaluate: wrote the BOP results CSV {r['csv']}")
    elif test is not None and test["kind"] == "capture_session":
        name = args.name or "turntable"
        r = evaluate_session(args.model, args.test, object_model_dir=args.object_model, name=name,
                             precision=args.precision, refine=refine, progress=_progress_bar("evaluate"))
    else:
        name = args.name or "synthetic"
        r = evaluate(args.model, args.test, name=name, precision=args.precision, max_frames=args.frames,
                     refine=refine, progress=_progress_bar("evaluate"))
    print(f"evaluate: {r['detected']}/{r['instances']} instances detected in {r['images']} images ({args.precision}), "
          f"{r['false_detections']} false detections")
    print(f"evaluate: ADD-S accuracy {100 * r['adds_accuracy_10pct']:.1f} %, ADD {100 * r['add_accuracy_10pct']:.1f} % "
          f"(10 % of the {r['diameter_mm']:.0f} mm diameter); AUC to 10 cm: ADD-S {100 * r['adds_auc_10cm']:.1f}, "
          f"ADD {100 * r['add_auc_10cm']:.1f}")
    print(f"evaluate: network {r['network_ms_mean']:.1f} ms, post-processing {r['postprocess_ms_mean']:.1f} ms"
          + (f", refinement {r['refine_ms_mean']:.1f} ms" if r.get("refined") else "") + " per frame")
    print(f"evaluate: wrote {args.model}/eval.json ({name}/{args.precision}) and eval_{name}.png")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="n2d", description="n2d: from an object on a turntable to a live 6D pose estimator (ROS 2).",
        epilog="Run 'n2d COMMAND --help' for the options of a command.")
    parser.add_argument("--version", action="version", version=f"n2d {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("demo", help="run the whole job on the embedded simulated world (no hardware)",
                       description="Start the simulated turntable world (Dynamixel servo emulated on a pty + "
                       "rendered camera) with every stage node, run the Pipeline action (empty-plate sweep, capture, "
                       "test sweep, reconstruction, dataset, DOPE training, evaluation) into one run directory, then "
                       "score dope_node's live poses against the simulator's ground truth. Ctrl-C and the same "
                       "command continues from the last finished stage; a finished demo does nothing unless "
                       "--overwrite.")
    p.add_argument("out", nargs="?", type=Path, default=Path("n2d_runs/demo"),
                   help="run directory (default: n2d_runs/demo)")
    p.add_argument("--overwrite", action="store_true", help="discard the run directory's results and start over")
    _add_config_options(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("board", help="write a print-ready ChArUco board (PDF + PNG + spec) for the plate",
                       description="Write board.pdf (exact physical size: print at 100 %%), board.png (with its "
                       "resolution) and board.json (the spec capture reads). Size it with --set, e.g. "
                       "--set squares_x=6 --set square_m=0.035 --set plate_diameter_m=0.30.")
    p.add_argument("out", type=Path, help="output directory")
    p.add_argument("--dpi", type=int, default=300, help="resolution of the PNG and of the image in the PDF")
    _add_config_options(p)
    p.set_defaults(func=cmd_board)

    p = sub.add_parser("capture", help="sweep the turntable and write a posed, masked capture session",
                       description="Turn the plate through --views stops and take a fresh frame at each. Run "
                       "once with --empty on the empty plate (the background reference), then place the object "
                       "and run again: the object sweep, camera poses from the ChArUco board (metric, in the "
                       "turntable frame) and masks. A stopped sweep resumes when run again. With --set placements=2 it "
                       "asks for the object to be turned over after the first sweep (press Enter) and sweeps again: "
                       "the reconstruction then sees the underside too.")
    p.add_argument("session", type=Path, help="capture session directory")
    p.add_argument("--empty", action="store_true", help="record the empty-plate sweep")
    p.add_argument("--views", type=int, default=0, help="stops per revolution (default: the config's, 36)")
    p.add_argument("--camera", default="ros", help="ros[:IMAGE_TOPIC] (default /n2d/camera/image_raw) or "
                   "cv:DEVICE_INDEX_OR_VIDEO_FILE")
    p.add_argument("--port", default="/dev/ttyUSB0", help="serial port of the turntable servo")
    p.add_argument("--baud", type=int, default=57600, help="servo baud rate")
    p.add_argument("--servo-id", type=int, default=1, help="servo Dynamixel ID")
    p.add_argument("--rotate-action", default="", help="turn the plate through this Rotate action (e.g. "
                   "/n2d/turntable/rotate, when turntable_node owns the port) instead of --port")
    p.add_argument("--overwrite", action="store_true", help="discard an existing or unfinished session")
    p.add_argument("--board", type=Path, help="board.json of the printed board (from n2d board; default: the "
                   "default board)")
    _add_config_options(p)
    p.set_defaults(func=cmd_capture)

    p = sub.add_parser("capture-import", aliases=["capture import"],
                       help="turn a folder of photos taken elsewhere into a capture session (n2d capture import)",
                       description="Import stills (DSLR, phone, another turntable) with the ChArUco board in view: "
                       "the same board, pose and mask code as a capture. Optional: empty-plate photos taken at the "
                       "same angles (--empty), per-photo plate angles in PHOTOS/angles.csv (file,angle_deg) or "
                       "angles.json, and the camera intrinsics (--intrinsics; default: calibrated from the board). "
                       "Photos where the object hides the board: --set pose_from=colmap (structure from motion on "
                       "the object; without the board in 3+ photos also --set sfm.camera_distance_m=METRES). "
                       "--from nerfstudio|colmap imports views posed elsewhere (transforms.json, a COLMAP sparse "
                       "model): the turntable frame from the camera ring and the board, metric from the board or "
                       "--scale-from; their masks are used where they have them.")
    p.add_argument("photos", type=Path, help="folder of .jpg/.png photos (sorted by name), or with --from the "
                   "nerfstudio dataset (holds transforms.json) or COLMAP folder (images/, sparse/0/)")
    p.add_argument("out", type=Path, help="capture session directory to write")
    p.add_argument("--from", dest="source", choices=("photos", "nerfstudio", "colmap"), default="photos",
                   help="what PHOTOS holds: photos (default), posed views of nerfstudio or of COLMAP")
    p.add_argument("--scale-from", metavar="cam:IMG_A,IMG_B=METRES", help="with --from: the known distance "
                   "between two views' camera centres makes the session metric (default: the board in 3+ views)")
    p.add_argument("--empty", type=Path, help="folder of empty-plate photos, same count and order")
    p.add_argument("--intrinsics", type=Path, help="intrinsics JSON/YAML (n2d or ROS camera_info format)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing session")
    p.add_argument("--board", type=Path, help="board.json of the printed board (from n2d board)")
    _add_config_options(p)
    p.set_defaults(func=cmd_capture_import)

    p = sub.add_parser("reconstruct", help="turn a capture session into a textured, metric mesh",
                       description="Reconstruct the object of a capture session: geometry (fast: visual hull of the "
                       "masks refined by photo-consistency, CPU, minutes; neus: a NeuS hash-grid SDF trained from the "
                       "hull, CUDA when present, with a checkpoint a re-run resumes from), mesh, UV atlas and albedo "
                       "(from the photos, or NeuS's colour field), in metres in the object frame (bounding-box "
                       "centre, Z up), plus models_info.json, report.json (held-out PSNR/SSIM/"
                       "FLIP, Chamfer against --ground-truth) and preview.png.")
    p.add_argument("session", type=Path, help="capture session directory")
    p.add_argument("out", type=Path, help="model directory to write")
    p.add_argument("--method", choices=["fast", "neus"], help="reconstruction method (default: the config's, fast)")
    p.add_argument("--neus-preset", choices=["tiny", "cpu", "gpu"], default="cpu",
                   help="NeuS size: cpu (2 cores, tens of minutes), gpu (the paper's scale), tiny (tests)")
    p.add_argument("--name", help="object name (default: the config's object_name)")
    p.add_argument("--ground-truth", type=Path, help="model directory of the true object (the simulator's sample "
                   "objects) standing at the plate centre: measure Chamfer and F-score")
    p.add_argument("--overwrite", action="store_true", help="replace an existing model (once the new one is done)")
    _add_config_options(p)
    p.set_defaults(func=cmd_reconstruct)

    p = sub.add_parser("model-import", aliases=["model import"],
                       help="turn a mesh file (OBJ, PLY, GLB/glTF, STL) into a model directory (n2d model import)",
                       description="Bring your own mesh: an OBJ with its MTL and texture, a PLY with vertex colours, "
                       "a GLB/glTF or an STL becomes a model directory as n2d reconstruct writes it (metres, object "
                       "frame at the bounding-box centre, Z up, the colours baked into a UV atlas, symmetries "
                       "detected), for n2d dataset and n2d train. The units are read from the size (a diameter of "
                       "0.01-1.5 in the file is metres, 1.5-20 centimetres, 20-1500 millimetres) unless --units "
                       "gives them; n2d.json records them and T_source_object, the object frame in the file's frame.")
    p.add_argument("mesh", type=Path, help="mesh file (.obj, .ply, .glb, .gltf, .stl, .off)")
    p.add_argument("out", type=Path, help="model directory to write")
    p.add_argument("--units", choices=["auto", "m", "cm", "mm", "in"], help="unit of the file's numbers "
                   "(default: the config's, auto)")
    p.add_argument("--up", choices=["auto", "x", "y", "z", "-x", "-y", "-z"], help="the file's up axis, turned "
                   "to +Z (default auto: y for glTF, z otherwise)")
    p.add_argument("--colour", type=_rgb, metavar="R,G,B", help="colour (0..255) of a mesh without texture or "
                   "vertex colours (default: its material's, else grey)")
    p.add_argument("--name", help="object name (default: the file name)")
    p.add_argument("--symmetry", choices=["auto", "none"], help="detect the symmetries (auto, default) or "
                   "write none")
    p.add_argument("--overwrite", action="store_true", help="replace an existing model (once the new one is done)")
    _add_config_options(p)
    p.set_defaults(func=cmd_model_import)

    p = sub.add_parser("dataset", help="render a domain-randomised, annotated dataset (BOP + DOPE) of models",
                       description="Render random scenes of the models (random floors, walls, distractors, lights, "
                       "objects standing as captured or resting on a face, optional in-hand gripper) with Cycles, or "
                       "with the fast rasterizer (--set render.engine=raster, ten times the frames per CPU-hour; "
                       "photoreal_frames of them by Cycles), and write BOP train_pbr chunks (rgb, "
                       "depth, mask, mask_visib, scene_gt, scene_camera, scene_gt_info) with a DOPE JSON beside "
                       "each image, models/, camera.json and contact_sheet.png. Ctrl-C keeps finished frames; the "
                       "same command resumes. Seeded: the same config renders the same frames.")
    p.add_argument("models", type=Path, nargs="+", help="model directories (from n2d reconstruct)")
    p.add_argument("out", type=Path, help="dataset directory to write")
    p.add_argument("--frames", type=int, help="frames to render (default: the config's, 100)")
    p.add_argument("--workers", type=int, help="render processes (default 0: automatic, the fastest on a CPU)")
    p.add_argument("--seed", type=int, help="seed of every random choice (default 0)")
    p.add_argument("--cluster", metavar="ADDRESS", help="render on a Ray cluster: ray://HEAD:10001 (Ray Client), "
                   "HEAD:6379 (from a node of the cluster), auto (the cluster this machine joined) or local (a "
                   "one-machine cluster); the frames come back into OUT, --workers counts Ray worker slots")
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset, or discard unfinished "
                   "work of another config")
    _add_config_options(p)
    p.set_defaults(func=cmd_dataset)

    p = sub.add_parser("train", help="train a DOPE network for one object of a dataset and export it to ONNX",
                       description="Train DOPE (belief maps of the cuboid's 8 corners + centroid, affinity fields, "
                       "intermediate supervision) on a dataset from n2d dataset, with sim-to-real augmentation, then "
                       "export model.onnx (+ model_int8.onnx, calibrated on training frames) and config.json. "
                       "Backbones: lite (EfficientNet-Lite0 with ImageNet weights, real time on a CPU) or vgg (DOPE as "
                       "published, needs a GPU). CUDA when present. Ctrl-C saves a checkpoint; the same command "
                       "resumes.")
    p.add_argument("dataset", type=Path, nargs="+", help="dataset directory (from n2d dataset); several, rendered "
                   "with the same camera, train on all their frames")
    p.add_argument("out", type=Path, help="DOPE model directory to write")
    p.add_argument("--object", help="object to train for (default: the dataset's only object)")
    p.add_argument("--init", type=Path, help="start from this DOPE model's weights instead of ImageNet's "
                   "(fine-tune it on more or newer data)")
    p.add_argument("--backbone", choices=["lite", "vgg", "tiny"], default="lite",
                   help="preset: lite (CPU), vgg (DOPE as published: 6 stages, batch 64, lr 1e-4), tiny (tests)")
    p.add_argument("--epochs", type=int, help="passes over the training frames (default: the preset's)")
    p.add_argument("--minutes", type=float, help="train for this many minutes (the learning rate anneals over "
                   "them; the preset's epochs do not stop it, an explicit --epochs does), then export")
    p.add_argument("--ddp", type=int, default=0, metavar="N", help="train data-parallel in N processes of this "
                   "machine (torch.distributed: gloo on CPUs, NCCL on GPUs; the same batches and checkpoints). On "
                   "several machines launch with torchrun instead")
    p.add_argument("--overwrite", action="store_true", help="replace an existing model, or discard unfinished "
                   "training of another config")
    _add_config_options(p)
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("pipeline", help="run the pipeline of several objects, here or on a Ray cluster",
                       description="Run the stages after the captures (reconstruct, dataset, test_dataset, train, "
                       "evaluate) for each object of --objects into RUN_DIR/NAME, one after another on this "
                       "machine or one object per cluster node at a time with --cluster. An object is a run "
                       "directory already in RUN_DIR (captured with the Pipeline action) or NAME=SOURCE: a capture "
                       "session or a model directory, copied in as its capture/ or model/. One object's failure is "
                       "reported and the others finish (exit code 2); the same command resumes each object. Config "
                       "values (--config, --set) are those of the Pipeline action's config, the same for every "
                       "object. With --cluster, RUN_DIR must be on a filesystem every node mounts at the same path.")
    p.add_argument("run_dir", type=Path, help="folder of the objects' run directories (RUN_DIR/NAME)")
    p.add_argument("--objects", required=True, metavar="NAME[=SOURCE],...", help="the objects, comma-separated, "
                   "e.g. mug,box=models/box")
    p.add_argument("--stages", metavar="STAGE,...", help="run only these stages (default: every stage after the "
                   "captures)")
    p.add_argument("--cluster", metavar="ADDRESS", help="run the objects as tasks on a Ray cluster: "
                   "ray://HEAD:10001, HEAD:6379, auto or local (as n2d dataset --cluster)")
    _add_config_options(p)
    p.set_defaults(func=cmd_pipeline)

    p = sub.add_parser("evaluate", help="measure a DOPE model: ADD / ADD-S accuracy and AUC on a test set",
                       description="Run the model on a test set it was not trained on and compare with the ground "
                       "truth: ADD and ADD-S accuracy at 10 %% of the object diameter, AUC up to 10 cm, per-frame "
                       "timings. The test set is a dataset (n2d dataset with another seed) or a capture session (a "
                       "turntable sweep at angles not used for the reconstruction, object not moved: ground truth "
                       "from the board). Writes MODEL/eval.json (under NAME/PRECISION) and MODEL/eval_NAME.png.")
    p.add_argument("model", type=Path, help="DOPE model directory (from n2d train)")
    p.add_argument("test", type=Path, help="test dataset or capture session directory, or a BOP dataset with "
                   "--object-id")
    p.add_argument("--name", help="name of this test set in eval.json (default: synthetic or turntable)")
    p.add_argument("--precision", choices=["fp32", "int8"], default="fp32", help="which exported model to run")
    p.add_argument("--frames", type=int, default=0, help="dataset: evaluate only the first N frames (0: all)")
    p.add_argument("--refine", action="store_true", help="refine each detected pose against the image with the "
                   "object's model (region-based, as dope_node does) and drop poses that do not fit")
    p.add_argument("--object-id", type=int, help="score on a BOP-format dataset (TEST is its directory): the "
                   "object's id there (models/obj_NNNNNN.ply); also writes BOP's results CSV")
    p.add_argument("--split", default="test", help="BOP: the split (default test)")
    p.add_argument("--targets", type=Path, help="BOP: a test_targets_bop19.json picking the images")
    p.add_argument("--object-model", type=Path, help="capture session: the object's model directory from n2d "
                   "reconstruct (records where it stood on the plate; default: the model DOPE was trained on)")
    p.set_defaults(func=cmd_evaluate)

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
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:2] in (["capture", "import"], ["model", "import"]):
        argv[:2] = [f"{argv[0]}-import"]
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except N2DError as exc:
        _close_progress_bars()
        print(f"n2d: error: {exc.message}", file=sys.stderr)
        if exc.hint:
            print(f"  hint: {exc.hint}", file=sys.stderr)
        return 2
    except OSError as exc:
        _close_progress_bars()
        where = f": {exc.filename}" if exc.filename else ""
        print(f"n2d: error: {exc.strerror or exc}{where}", file=sys.stderr)
        print("  hint: check free disk space and permissions; finished work is kept", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        _close_progress_bars()
        print("n2d: interrupted; finished work is kept and the same command resumes it", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
