"""Capture folders: RGB-D frames of a vine with their camera model and, optionally, robot poses.

Layout (docs/capture-format.md):

    CAPTURE/
      capture.json      format "vinetwin-capture", version 1, camera (CameraModel fields),
                        depth_unit (metres per depth count), optional T_flange_camera (hand-eye),
                        frames: [{id, color, depth, T_base_camera | T_base_flange, stamp}]
      color/ID.png      8-bit RGB
      depth/ID.png      16-bit z-depth, 0 = no data

Reading checks what would otherwise turn into a bad mesh, naming the frame: a missing or
unreadable file, an image whose size does not match the intrinsics, a depth unit that puts the
median depth outside 2 cm - 2 m (wrong unit), too few frames.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from vinetwin.camera import CameraModel
from vinetwin.errors import InputError
from vinetwin.files import atomic_write_text, read_json
from vinetwin.frames import Array, check_pose

CAPTURE_FORMAT = "vinetwin-capture"
CAPTURE_VERSION = 1
MIN_FRAMES = 3


class CaptureError(InputError):
    """A capture folder that cannot be used, with the frame (or field) at fault."""


@dataclass
class Frame:
    id: str
    color_path: Path | None
    """None when the frame has no colour image."""
    depth_path: Path
    T_base_camera: Array | None = None
    """The camera in the robot base (from kinematics and the hand-eye transform), if known."""
    stamp: float | None = None
    """When the frame was taken (s), if recorded."""

    def depth_counts(self) -> npt.NDArray[np.uint16]:
        """The depth image as stored: counts of the capture's depth unit (0 = no data)."""
        img = _read_png(self.depth_path, f"frame {self.id}: depth")
        if img.dtype != np.uint16 or img.ndim != 2:
            raise CaptureError(
                f"frame {self.id}: depth {self.depth_path.name} must be a 16-bit single-channel "
                f"PNG, got {img.dtype} with shape {img.shape}"
            )
        return np.ascontiguousarray(img)

    def depth(self, depth_unit: float) -> npt.NDArray[np.float32]:
        """z-depth in metres (0 where the sensor gave nothing)."""
        return self.depth_counts().astype(np.float32) * np.float32(depth_unit)

    def color(self) -> npt.NDArray[np.uint8]:
        if self.color_path is None:
            raise CaptureError(f"frame {self.id}: no colour image was recorded")
        img = _read_png(self.color_path, f"frame {self.id}: colour")
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        return np.ascontiguousarray(img[..., :3]).astype(np.uint8)


@dataclass
class Capture:
    root: Path
    camera: CameraModel
    depth_unit: float
    frames: list[Frame] = field(default_factory=list)
    T_flange_camera: Array | None = None

    @property
    def has_poses(self) -> bool:
        return all(f.T_base_camera is not None for f in self.frames)


def _read_png(path: Path, what: str) -> np.ndarray:
    import imageio.v3 as iio

    try:  # a name too long for the file system, or a path through a file, raises here
        present = path.is_file()
    except OSError as exc:
        raise CaptureError(
            f"{what}: {str(path)[:200]} is not a usable path: {exc.strerror}"
        ) from exc
    if not present:
        raise CaptureError(f"{what}: {str(path)[:200]} is missing")
    try:
        return np.asarray(iio.imread(path))
    except Exception as exc:
        raise CaptureError(f"{what}: cannot read {path}: {exc}") from exc


def read_capture(root: str | Path, check_frames: bool = True) -> Capture:
    """Reads and checks a capture folder; raises CaptureError naming what is wrong."""
    root = Path(root)
    meta_path = root / "capture.json"
    if not meta_path.exists():
        raise CaptureError(f"{root}: no capture.json here; is this a capture folder?")
    meta = read_json(meta_path, CaptureError)
    try:
        cap = _capture_from(root, meta_path, meta)
    except CaptureError:
        raise
    except InputError as exc:  # a pose that is not one: the file named
        raise CaptureError(f"{meta_path}: {exc}") from None
    except (KeyError, TypeError, ValueError, AttributeError) as exc:  # a field of a wrong type
        raise CaptureError(f"{meta_path}: malformed: {type(exc).__name__}: {exc}") from None
    if check_frames:
        check_capture(cap)
    return cap


def _capture_from(root: Path, meta_path: Path, meta: Any) -> Capture:
    """The capture that capture.json's content describes (frames not read)."""
    if not isinstance(meta, dict):
        raise CaptureError(
            f"{meta_path}: a capture.json is a JSON object, got {type(meta).__name__}"
        )
    if meta.get("format") != CAPTURE_FORMAT:
        raise CaptureError(
            f"{meta_path}: format must be '{CAPTURE_FORMAT}', got {meta.get('format')!r}"
        )
    version = meta.get("format_version", 0)
    if (
        isinstance(version, bool)
        or not isinstance(version, (int, float))
        or not math.isfinite(version)
        or version != int(version)
        or version < 0
    ):
        raise CaptureError(
            f"{meta_path}: format_version must be a whole number >= 0, got {version!r}"
        )
    if version > CAPTURE_VERSION:
        raise CaptureError(
            f"{meta_path}: format version {meta['format_version']} is newer than this vinetwin reads ({CAPTURE_VERSION})"
        )
    try:
        camera = CameraModel.from_dict(meta["camera"])
        unit = float(meta["depth_unit"])
    except (KeyError, TypeError, ValueError) as exc:
        raise CaptureError(f"{meta_path}: camera or depth_unit missing or invalid: {exc}") from exc
    if not unit > 0:
        raise CaptureError(f"{meta_path}: depth_unit must be positive, got {unit}")
    T_fc = None
    if meta.get("T_flange_camera") is not None:
        T_fc = check_pose(meta["T_flange_camera"], "T_flange_camera")
    frames = []
    for i, fm in enumerate(meta.get("frames", [])):
        fid = str(fm.get("id", i))
        T = None
        if fm.get("T_base_camera") is not None:
            T = check_pose(fm["T_base_camera"], f"frame {fid}: T_base_camera")
        elif fm.get("T_base_flange") is not None:
            if T_fc is None:
                raise CaptureError(
                    f"frame {fid}: T_base_flange given but no T_flange_camera (hand-eye) in capture.json"
                )
            T = check_pose(fm["T_base_flange"], f"frame {fid}: T_base_flange") @ T_fc
        if "depth" not in fm:
            raise CaptureError(f"frame {fid}: no depth image listed")
        stamp = fm.get("stamp")
        if stamp is not None and not (isinstance(stamp, int | float) and math.isfinite(stamp)):
            raise CaptureError(f"frame {fid}: stamp must be a finite number, got {stamp!r}")
        color = root / fm["color"] if fm.get("color") else None
        frames.append(Frame(fid, color, root / fm["depth"], T, stamp))
    if len(frames) < MIN_FRAMES:
        raise CaptureError(f"{root}: {len(frames)} frames; at least {MIN_FRAMES} are needed")
    return Capture(root, camera, unit, frames, T_fc)


def check_capture(cap: Capture) -> None:
    """Checks every frame's files, sizes and the plausibility of the depth unit."""
    medians = []
    for f in cap.frames:
        d = f.depth(cap.depth_unit)
        if d.shape != (cap.camera.height, cap.camera.width):
            raise CaptureError(
                f"frame {f.id}: depth is {d.shape[1]}x{d.shape[0]} but the intrinsics are for "
                f"{cap.camera.width}x{cap.camera.height}"
            )
        if f.color_path is not None:
            c = f.color()
            if c.shape[:2] != d.shape:
                raise CaptureError(
                    f"frame {f.id}: colour is {c.shape[1]}x{c.shape[0]}, depth {d.shape[1]}x{d.shape[0]}"
                )
        valid = d[d > 0]
        if valid.size:
            medians.append(float(np.median(valid)))
    if not medians:
        raise CaptureError(f"{cap.root}: no frame holds any depth")
    med = float(np.median(medians))
    if not 0.02 <= med <= 2.0:
        raise CaptureError(
            f"{cap.root}: median depth {med:.4g} m with depth_unit {cap.depth_unit} is implausible for "
            "a D405 (0.07-0.5 m): wrong depth unit?"
        )


class CaptureWriter:
    """Writes a capture folder frame by frame (a recording of any length without holding it in
    memory); `capture.json` is rewritten atomically every `flush_every` frames and at `close`,
    so an interrupted recording keeps the frames listed so far."""

    def __init__(
        self,
        root: str | Path,
        camera: CameraModel,
        depth_unit: float = 1e-4,
        extra: dict[str, Any] | None = None,
        flush_every: int = 30,
    ) -> None:
        self.root = Path(root)
        (self.root / "color").mkdir(parents=True, exist_ok=True)
        (self.root / "depth").mkdir(parents=True, exist_ok=True)
        self.camera = camera
        self.depth_unit = depth_unit
        self.extra = extra or {}
        self.flush_every = flush_every
        self.listed: list[dict[str, Any]] = []

    def add(
        self,
        counts: np.ndarray,
        color: np.ndarray | None = None,
        T_base_camera: Array | None = None,
        stamp: float | None = None,
    ) -> None:
        """One frame: depth in counts of the depth unit (uint16), optional colour, pose, stamp."""
        import imageio.v3 as iio

        fid = f"{len(self.listed):06d}"
        iio.imwrite(self.root / "depth" / f"{fid}.png", np.asarray(counts, np.uint16))
        entry: dict[str, Any] = {"id": fid, "depth": f"depth/{fid}.png"}
        if color is not None:
            iio.imwrite(self.root / "color" / f"{fid}.png", np.asarray(color, np.uint8))
            entry["color"] = f"color/{fid}.png"
        if T_base_camera is not None:
            entry["T_base_camera"] = np.asarray(T_base_camera).tolist()
        if stamp is not None:
            entry["stamp"] = float(stamp)
        self.listed.append(entry)
        if len(self.listed) % self.flush_every == 0:
            self.flush()

    def flush(self) -> None:
        meta = {
            "format": CAPTURE_FORMAT,
            "format_version": CAPTURE_VERSION,
            "camera": self.camera.to_dict(),
            "depth_unit": self.depth_unit,
            **self.extra,
            "frames": self.listed,
        }
        atomic_write_text(self.root / "capture.json", json.dumps(meta, indent=1) + "\n")

    def close(self) -> Path:
        self.flush()
        return self.root


def write_capture(
    root: str | Path,
    camera: CameraModel,
    frames: Sequence[tuple[np.ndarray, np.ndarray, Array | None]],
    depth_unit: float = 1e-4,
    extra: dict[str, Any] | None = None,
) -> Path:
    """Writes (colour uint8 HxWx3, depth metres HxW, T_base_camera or None) frames as a capture."""
    w = CaptureWriter(root, camera, depth_unit, extra, flush_every=10**9)
    for color, depth, T in frames:
        d = np.asarray(depth, dtype=np.float64)
        counts = np.where(np.isfinite(d) & (d > 0), np.round(d / depth_unit), 0)
        w.add(np.clip(counts, 0, 65535).astype(np.uint16), color, T)
    return w.close()
