"""KITTI 3D object frames: ``<root>/<split>/{velodyne|velodyne_reduced, calib, label_2}/NNNNNN.*``.

Points are the Velodyne cloud (x forward, y left, z up, metres; reflectance in [0, 1]).
Labels are in the rectified camera-2 frame (x right, y down, z forward) with ``(x, y, z)``
the centre of the box's bottom face; they are moved into the Velodyne frame with
``inv(R0_rect @ Tr_velo_to_cam)`` (both padded to 4x4): centre_cam = (x, y - h/2, z),
yaw_lidar = -rotation_y - pi/2, size (l, w, h). ``DontCare`` rows are skipped.

A ``.bin`` has no header, so another dataset's cloud can pass for a KITTI one. What is
detectable, and refused: a size that is no multiple of 16 bytes; coordinates beyond
:data:`~typ.formats.binfile.MAX_ABS_COORDINATE` or not finite (float64, big-endian, the
microsecond timestamps of a Waymo x6 file landing in x, y, z); and a reflectance outside
[0, 1], KITTI's range. A nuScenes x5 file (``x y z intensity ring``, intensity 0..255) whose
point count is a multiple of 4 has a multiple of 16 bytes, and its rows read four floats
out of phase: the fourth column then holds, in turn, intensity, z, y, x and ring index, so
any real scan puts values outside [0, 1] there. Not detectable: a float32 x4 cloud of another
sensor whose fourth column happens to lie in [0, 1], or one in another frame within 10 km.
Calibration matrices must be near-rotations (``R0_rect``; the rotation part of
``Tr_velo_to_cam``): singular values within :data:`RIGID_TOLERANCE` of 1, so a singular or
scaled matrix is refused where it is read, not met as a LinAlgError when labels are moved.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from typ import geometry
from typ.errors import TypError
from typ.formats.binfile import read_bin
from typ.inputs import MiB, inside, read_text
from typ.scene import AgentView, Scene

_CALIB_SHAPES = {"R0_rect": (3, 3), "Tr_velo_to_cam": (3, 4)}
_LABEL_FIELDS = 15  # type truncated occluded alpha x1 y1 x2 y2 h w l x y z rotation_y (+ score)
#: No labelled object is longer than this (metres): larger sizes are centimetres or garbage.
MAX_BOX_SIZE = 100.0
#: calib and label files are a few KB
MAX_TEXT_BYTES = 1 * MiB
#: how far a calibration rotation's singular values may stray from 1 (KITTI's: about 1e-4)
RIGID_TOLERANCE = 0.1
#: a split folder or frame id: one name, never a path
_PLAIN_NAME = re.compile(r"[A-Za-z0-9._-]{1,128}")


def read_calib(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """KITTI object calib -> ``{name: float64 matrix}``; ``R0_rect`` (3, 3), ``Tr_velo_to_cam`` (3, 4) required.

    Other keys (``P0``..``P3``, ``Tr_imu_to_velo``) come back as flat float64 vectors
    reshaped to (3, 4) when they have 12 numbers.
    """
    p = Path(path)
    lines = read_text(p, "KITTI calib file", max_bytes=MAX_TEXT_BYTES, encoding="ascii").splitlines()
    calib: dict[str, np.ndarray] = {}
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        if not sep:
            raise TypError(p, f"line {number}", "'NAME: v1 v2 ...'", line[:80])
        try:
            values = np.array([float(v) for v in rest.split()], dtype=np.float64)
        except ValueError:
            raise TypError(p, key.strip(), "numbers", rest.strip()[:80]) from None
        calib[key.strip()] = values.reshape(3, 4) if values.size == 12 else values
    for key, shape in _CALIB_SHAPES.items():
        if key not in calib:
            raise TypError(p, key, f"a line '{key}: ' with {shape[0] * shape[1]} numbers", "missing")
        if calib[key].size != shape[0] * shape[1]:
            raise TypError(p, key, f"{shape[0] * shape[1]} numbers", calib[key].size)
        calib[key] = calib[key].reshape(shape)
        if not np.isfinite(calib[key]).all():
            raise TypError(p, key, "finite numbers", calib[key].ravel().tolist())
        stretch = np.linalg.svd(calib[key][:3, :3], compute_uv=False)
        if np.abs(stretch - 1.0).max() > RIGID_TOLERANCE:
            raise TypError(p, key, f"a rotation{' and a translation' if shape[1] == 4 else ''} "
                           f"(singular values 1 +- {RIGID_TOLERANCE:g})",
                           f"singular values {np.round(stretch, 4).tolist()}")
    return calib


def velo_to_rect(calib: dict[str, np.ndarray]) -> np.ndarray:
    """(4, 4) float64 Velodyne -> rectified camera-2: ``R0_rect @ Tr_velo_to_cam``, padded."""
    r0 = np.eye(4)
    r0[:3, :3] = calib["R0_rect"]
    tr = np.eye(4)
    tr[:3, :] = calib["Tr_velo_to_cam"]
    return r0 @ tr


def read_labels(path: str | os.PathLike, calib: dict[str, np.ndarray]) -> tuple[np.ndarray, tuple[str, ...]]:
    """label_2 file -> ``(K, 7)`` float64 boxes in the Velodyne frame and K lower-case class names."""
    p = Path(path)
    lines = read_text(p, "KITTI label file", max_bytes=MAX_TEXT_BYTES, encoding="ascii").splitlines()
    # the matrix is affine but not exactly rigid (R0_rect, calibration noise): use a general inverse
    rect_to_velo = np.linalg.inv(velo_to_rect(calib))
    boxes, labels = [], []
    for number, line in enumerate(lines, start=1):
        parts = line.split()
        if not parts or parts[0] == "DontCare":
            continue
        if len(parts) not in (_LABEL_FIELDS, _LABEL_FIELDS + 1):
            raise TypError(p, f"line {number}", f"{_LABEL_FIELDS} fields (type ... rotation_y [score])", len(parts))
        try:
            h, w, l, x, y, z, ry = (float(v) for v in parts[8:15])
        except ValueError:
            raise TypError(p, f"line {number}", "numbers in fields 9-15 (h w l x y z rotation_y)",
                           parts[8:15]) from None
        if not all(np.isfinite([h, w, l, x, y, z, ry])):
            raise TypError(p, f"line {number}", "finite numbers in fields 9-15 (h w l x y z rotation_y)",
                           parts[8:15])
        if min(h, w, l) <= 0:
            raise TypError(p, f"line {number}", "positive h, w, l", (h, w, l))
        if max(h, w, l) > MAX_BOX_SIZE:
            raise TypError(p, f"line {number}", f"h, w, l <= {MAX_BOX_SIZE:g} m (metres, not centimetres)", (h, w, l))
        centre = rect_to_velo @ np.array([x, y - h / 2.0, z, 1.0])
        boxes.append([*centre[:3], l, w, h, float(geometry.wrap_angle(-ry - np.pi / 2.0))])
        labels.append(parts[0].lower())
    return np.array(boxes, dtype=np.float64).reshape(-1, 7), tuple(labels)


def read_velodyne(path: str | os.PathLike) -> np.ndarray:
    """A KITTI velodyne ``.bin`` -> (N, 4) float32 ``[x, y, z, reflectance]``, reflectance in [0, 1]
    (see the module doc for what this can and cannot tell from another dataset's file)."""
    points = read_bin(path, 4)
    outside = (points[:, 3] < 0.0) | (points[:, 3] > 1.0)
    if outside.any():
        raise TypError(path, "reflectance", "values in [0, 1] in the fourth column (KITTI's float32 x4 layout); "
                       "a nuScenes (x5) or Waymo (x6) file reads out of phase here",
                       f"{int(outside.sum())} of {len(points)} points outside, "
                       f"such as {float(points[outside, 3][0]):g}")
    return points


def read_kitti_frame(root: str | os.PathLike, frame_id: int | str, split: str = "training") -> Scene:
    """One KITTI frame as a single-agent Scene (agent ``"ego"``, pose identity = the Velodyne frame).

    Points come from ``velodyne/`` or, when that frame is absent, ``velodyne_reduced/``.
    Without ``label_2/`` (the testing split) the frame has no boxes and calib is not needed.
    Box ids are the label rows' order (0, 1, ...) after DontCare rows are dropped.
    ``split`` and ``frame_id`` are plain names, and every file read lies inside ``root``, links
    followed (:func:`typ.inputs.inside`): a frame id of a split file cannot lead elsewhere.
    """
    for field, value in (("split", split), ("frame_id", frame_id)):
        if not _PLAIN_NAME.fullmatch(str(value)) or str(value) in (".", ".."):
            raise TypError(root, field, "a plain name (letters, digits, '.', '_', '-'; no folders)", value)
    base = Path(root) / split
    name = f"{int(frame_id):06d}" if str(frame_id).isdigit() else str(frame_id)
    candidates = [inside(Path(split) / folder / f"{name}.bin", root) for folder in ("velodyne", "velodyne_reduced")]
    bin_path = next((c for c in candidates if c.is_file()), None)
    if bin_path is None:
        raise TypError(base, "velodyne", f"{name}.bin under velodyne/ or velodyne_reduced/", "not found")
    points = read_velodyne(bin_path)
    label_path = inside(Path(split) / "label_2" / f"{name}.txt", root)
    boxes, labels = np.zeros((0, 7)), ()
    if label_path.parent.is_dir():
        boxes, labels = read_labels(label_path, read_calib(inside(Path(split) / "calib" / f"{name}.txt", root)))
    view = AgentView(agent_id="ego", points=points, pose=np.eye(4), boxes=boxes, box_labels=labels,
                     box_ids=np.arange(len(boxes)), where=str(bin_path))
    return Scene(scenario=name, timestamp=name, agents={"ego": view}, dataset="kitti", split=split)
