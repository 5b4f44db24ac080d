"""Offline import: stills taken elsewhere (DSLR, phone, another turntable) into a capture session.

`import_photos()` writes the photos into the layout a capture sweep leaves (`images/NNNN.png` +
`images.json`, and `empty/` + `empty.json` for empty-plate photos), then runs the same
`process_session()` as `capture()`: ChArUco board poses, the fitted turntable frame, masks,
transforms.json, capture.json (with an `import` section naming the source files) and the contact sheet.

Inputs:
- Photos: the `.png`, `.jpg` and `.jpeg` files (any case, hidden ones skipped) of a folder, in name
  order, all of one size; JPEG EXIF orientation is applied, as a photo viewer shows them. The ChArUco
  board (`cfg.board`) lies on the plate under the object and the camera stays put while the plate turns.
- Empty-plate photos (optional, recommended: masks are much better with them): a second folder
  with as many photos, in the same name order, taken at the same plate angles without the object.
- Plate angles (optional): `angles_deg`, one per photo in name order, or else a file in the photos
  folder: `angles.csv`, rows `file,angle_deg` (a header row, blank lines and `#` comments are
  skipped), or `angles.json`, `{"IMG_0001.jpg": 0.0, ...}` or a list in name order (the argument
  wins over a file). Degrees, counter-clockwise seen from above, any zero. Every photo needs one; the
  empty-plate photos share them. Without angles each view is posed from its own board pose, and a
  view whose board the object hides is an error naming it (nothing else could place it); with angles
  such a view is posed from its angle, as the servo angle places it in a capture.
- Intrinsics (optional): a file of the camera's calibration, else the focal length is calibrated from
  the board in the photos (principal point at the image centre, square pixels, no distortion: all
  the board views are one plane). JSON/YAML of `Intrinsics.to_dict()` (`K`, `dist`, `width`,
  `height`), or a ROS camera_info YAML as camera_calibration writes it (`image_width`,
  `image_height`, `camera_matrix.data`, `distortion_coefficients.data`). Its size must be the photos'.

Nothing is left behind when the import fails: the half-written session is removed.
"""

from __future__ import annotations

import csv
import json
import math
import shutil
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from n2d_capture.calibration import Intrinsics
from n2d_capture.capture import CaptureConfig, process_session
from n2d_common.config import read_mapping, to_dict
from n2d_common.contracts import StageWriter, atomic_write_json, stage_output
from n2d_common.errors import ConfigError, ContractError
from n2d_common.images import write_png
from n2d_common.progress import Progress, ProgressFn, no_progress

PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg")
"""File name endings of photos (compared in lower case)."""
ANGLE_FILES = ("angles.csv", "angles.json")
"""Names of the plate-angle file in the photos folder."""
IMPORT_SHARE = 0.3
"""Part of the progress bar given to reading and converting the photos (the rest: processing)."""


def list_photos(directory: str | Path) -> list[Path]:
    """The photos of `directory` in name order; ContractError when it is missing or holds none."""
    directory = Path(directory)
    if not directory.is_dir():
        raise ContractError(f"photo folder {directory} does not exist", "check the path")
    # Hidden files are skipped: macOS leaves unreadable "._IMG_0001.JPG" companions on other file systems.
    photos = sorted(p for p in directory.iterdir()
                    if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES and not p.name.startswith("."))
    if not photos:
        raise ContractError(f"{directory} holds no photos ({', '.join(PHOTO_SUFFIXES)})",
                            "give the folder the photos are in; other formats: convert them to PNG or JPEG")
    return photos


def read_angles(photos_dir: str | Path, photos: list[Path]) -> tuple[list[float] | None, str | None]:
    """(plate angles in degrees, one per photo, and the file's name) from `angles.csv` or `angles.json` in
    `photos_dir`; (None, None) when it has neither."""
    found = [Path(photos_dir) / name for name in ANGLE_FILES if (Path(photos_dir) / name).is_file()]
    if not found:
        return None, None
    if len(found) > 1:
        raise ConfigError(f"{photos_dir} holds both {' and '.join(ANGLE_FILES)}", "keep one of them")
    path = found[0]
    if path.suffix == ".json":
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ConfigError(f"cannot read {path}: {exc}", "expected {\"IMG_0001.jpg\": 0.0, ...}") from None
        if isinstance(data, list):
            return _check_angles(data, len(photos), str(path)), path.name
        if not isinstance(data, dict):
            raise ConfigError(f"{path} must hold a mapping of file name to degrees, or a list",
                              "e.g. {\"IMG_0001.jpg\": 0.0, \"IMG_0002.jpg\": 10.0}")
        by_name = data
    else:
        by_name = {}
        with path.open(newline="") as f:
            for row_number, row in enumerate(csv.reader(f), 1):
                if not row or not "".join(row).strip() or row[0].lstrip().startswith("#"):
                    continue
                if len(row) != 2:
                    raise ConfigError(f"{path} row {row_number}: expected 2 columns (file,angle_deg), got {len(row)}")
                name, value = row[0].strip(), row[1].strip()
                try:
                    by_name[name] = float(value)
                except ValueError:
                    if by_name:  # only the first row may be a header
                        raise ConfigError(f"{path} row {row_number}: {value!r} is not an angle in degrees") from None
    names = [p.name for p in photos]
    missing = [n for n in names if n not in by_name]
    unknown = sorted(set(by_name) - set(names))
    if missing or unknown:
        raise ConfigError(f"{path} does not match the photos: "
                          + "; ".join(s for s in (f"no angle for {', '.join(missing)}" if missing else "",
                                                  f"no photo named {', '.join(unknown)}" if unknown else "") if s),
                          "give one row per photo, named as in the folder")
    return _check_angles([by_name[n] for n in names], len(photos), str(path)), path.name


def _check_angles(angles: list, count: int, where: str) -> list[float]:
    if len(angles) != count:
        raise ConfigError(f"{where}: {len(angles)} plate angles for {count} photos", "give one angle per photo")
    try:
        out = [float(a) for a in angles]
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: plate angles must be numbers (degrees)") from None
    if not all(math.isfinite(a) for a in out):
        raise ConfigError(f"{where}: plate angles must be finite")
    return out


def load_intrinsics(path: str | Path) -> Intrinsics:
    """Intrinsics from a JSON/YAML file: `Intrinsics.to_dict()`'s form, or a ROS camera_info YAML."""
    data = read_mapping(path)
    if "camera_matrix" not in data:
        return Intrinsics.from_dict(data)
    try:
        return Intrinsics(K=np.asarray(data["camera_matrix"]["data"], dtype=float).reshape(3, 3),
                          dist=np.asarray((data.get("distortion_coefficients") or {}).get("data", []), dtype=float),
                          width=int(data["image_width"]), height=int(data["image_height"]))
    except KeyError as exc:
        raise ConfigError(f"camera_info {path}: missing {exc.args[0]!r}", "expected image_width, image_height, "
                          "camera_matrix.data, distortion_coefficients.data") from None
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"camera_info {path}: {exc}", "camera_matrix.data must hold 9 numbers") from None


def read_photo(path: Path) -> np.ndarray:
    """RGB uint8 of a photo, EXIF orientation applied (8-bit, alpha dropped, grey made RGB)."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ContractError(f"cannot read photo {path}", "is it a valid PNG or JPEG file?")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _write_sweep(directory: Path, name: str, files: list[Path], angles_rad: list[float | None],
                 intr: Intrinsics | None, size: tuple[int, int] | None,
                 report: Callable[[int, Path], None]) -> tuple[int, int]:
    """Write photos as sweep `name` of a session (`<name>/NNNN.png`, `<name>.json`), as `run_sweep` does.

    Returns the (width, height) of the photos; all must have the same, `size` when it is given.
    """
    records = []
    for i, path in enumerate(files):
        report(i, path)
        rgb = read_photo(path)
        size = size or (rgb.shape[1], rgb.shape[0])
        if (rgb.shape[1], rgb.shape[0]) != size:
            raise ContractError(f"{path} is {rgb.shape[1]}x{rgb.shape[0]}, other photos are {size[0]}x{size[1]}",
                                "all photos must come from one camera setting, uncropped")
        file = f"{name}/{i:04d}.png"
        write_png(directory / file, rgb)
        stamp = path.stat().st_mtime
        record = {"index": i, "file": file, "angle_cmd_rad": angles_rad[i], "angle_rad": angles_rad[i],
                  "stamp_s": stamp, "settled_s": stamp, "source": path.name}
        if intr is not None:  # as a CameraInfo would give them
            record["K"], record["dist"] = intr.K.tolist(), intr.dist.tolist()
        records.append(record)
    atomic_write_json(directory / f"{name}.json", {"sweep": name, "views": records})
    return size


@contextmanager
def import_output(session_dir: str | Path, config: dict, overwrite: bool) -> Iterator[StageWriter]:
    """The session an import writes (`stage_output`), removed again when the import fails: an import is cheap
    to redo, so it leaves nothing half-made and never resumes."""
    with stage_output(session_dir, "capture_session", overwrite=overwrite, resume=False, config=config) as out:
        try:
            yield out
        except BaseException:
            shutil.rmtree(out.path, ignore_errors=True)
            raise


def import_photos(photos_dir: str | Path, session_dir: str | Path, cfg: CaptureConfig, *,
                  empty_dir: str | Path | None = None, angles_deg: Sequence[float] | None = None,
                  intrinsics: str | Path | None = None, overwrite: bool = False,
                  progress: ProgressFn = no_progress) -> dict:
    """Turn a folder of photos into a complete capture session at `session_dir` (see the module doc).

    Args:
        photos_dir: folder of the photos with the object.
        session_dir: the capture session to write.
        cfg: board spec, masks and pose thresholds; `intrinsics` and `sweep` are set from the import.
        empty_dir: folder of the empty-plate photos, as many as `photos_dir` holds, in the same order.
        angles_deg: plate angle of each photo, degrees, in name order (else from angles.csv/.json, if any).
        intrinsics: calibration file of the camera (else the focal length is calibrated from the board).
        overwrite: replace an existing session (only once the new one is complete).
        progress: progress reports.

    Returns:
        The summary of `process_session` plus "views" and "message".

    Raises:
        ContractError: a folder is missing or holds no photos, photos of different sizes, unequal
            photo counts, an existing output without `overwrite`.
        ConfigError: bad angles or intrinsics file.
        CalibrationError: too few board poses, or (without angles) views that hide the board.
    """
    photos_dir = Path(photos_dir)
    photos = list_photos(photos_dir)
    empties = list_photos(empty_dir) if empty_dir is not None else []
    if empty_dir is not None and len(empties) != len(photos):
        raise ContractError(f"{len(photos)} photos in {photos_dir} but {len(empties)} empty-plate photos in "
                            f"{empty_dir}", "take one empty-plate photo at the plate angle of each photo")
    if angles_deg is not None:
        angles, angles_from = _check_angles(list(angles_deg), len(photos), "angles_deg"), "argument"
    else:
        angles, angles_from = read_angles(photos_dir, photos)
    intr = load_intrinsics(intrinsics) if intrinsics is not None else None
    cfg = replace(cfg, intrinsics="camera_info" if intr is not None else "calibrate",
                  sweep=replace(cfg.sweep, views=len(photos)))
    angles_rad = [math.radians(a) for a in angles] if angles is not None else [None] * len(photos)
    total = len(photos) + len(empties)

    with import_output(session_dir, to_dict(cfg), overwrite) as out:
        def copying(done: int, path: Path) -> None:
            progress(Progress(IMPORT_SHARE * done / total, "importing", message=path.name))

        size = _write_sweep(out.path, "images", photos, angles_rad, intr, None, copying)
        if intr is not None and (intr.width, intr.height) != size:
            raise ConfigError(f"the intrinsics in {intrinsics} are for {intr.width}x{intr.height} images, the "
                              f"photos are {size[0]}x{size[1]}", "give the calibration of this camera setting")
        if empties:
            _write_sweep(out.path, "empty", empties, angles_rad, intr, size,
                         lambda done, path: copying(len(photos) + done, path))

        def processing(p: Progress) -> None:
            progress(replace(p, fraction=IMPORT_SHARE + (1 - IMPORT_SHARE) * p.fraction))

        summary = process_session(out.path, cfg, processing)
        info_path = out.path / "capture.json"
        info = json.loads(info_path.read_text())
        info["import"] = {"photos_dir": str(photos_dir.absolute()), "photos": [p.name for p in photos],
                          "empty_dir": str(Path(empty_dir).absolute()) if empty_dir is not None else None,
                          "empty_photos": [p.name for p in empties],
                          "angles_from": angles_from,
                          "intrinsics_file": str(Path(intrinsics).absolute()) if intrinsics is not None else None}
        atomic_write_json(info_path, info)
        inputs = {"photos": photos_dir.absolute()}
        if empty_dir is not None:
            inputs["empty"] = Path(empty_dir).absolute()
        out.finish(config=to_dict(cfg), inputs=inputs, extra=summary)
    return {"views": len(photos), "message": "", **summary}
