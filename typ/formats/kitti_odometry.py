"""LiDAR drives in the KITTI odometry / SemanticKITTI layout: scans with the pose of every one.

    <root>/sequences/<seq>/velodyne/NNNNNN.bin   float32 x, y, z, reflectance, the LiDAR's frame
    <root>/sequences/<seq>/calib.txt             ``Tr:`` 12 numbers, LiDAR -> camera 0 (3x4 row-major)
    <root>/sequences/<seq>/poses.txt             line k: camera 0's 3x4 row-major pose at scan k
                                                 (KITTI odometry's own layout: <root>/poses/<seq>.txt)
    <root>/sequences/<seq>/times.txt             optional, line k: scan k's time in seconds

The LiDAR pose of scan k is ``pose_k @ Tr`` (float64): the poses are camera 0's in the frame of
camera 0 at the first scan, and ``Tr`` carries the LiDAR into that camera. They are kept relative to
the first scan's LiDAR frame (``inv(L_0) @ L_k``), whose z is up, as a written lidar_pose needs.
Datasets written in this layout from another car (nuScenes through PRBonn's nuscenes2kitti) give
LiDAR poses and an identity ``Tr``, which reads the same. Scan k is the file ``{k:06d}.bin``: one
scan per pose line, numbered from 0 without gaps, as KITTI and SemanticKITTI number them.

:func:`read_sequence` checks a sequence whole before anything reads a point, each problem a
:class:`~typ.errors.TypError` naming the file and line: pose lines that are not one per scan, a
non-finite pose, a rotation that is not orthonormal, a ``calib.txt`` without ``Tr``, a scan whose
size is not a multiple of 16 bytes, times that are not one per scan, not finite or going back.
Every file it reads lies inside the dataset root once links are followed (:func:`typ.inputs.inside`).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from typ.errors import TypError
from typ.formats.binfile import read_bin
from typ.inputs import MiB, inside, read_text

#: poses.txt of KITTI's longest sequence (4,661 scans) is 0.7 MB; calib and times are smaller
MAX_TEXT_BYTES = 64 * MiB
#: a rotation's ``max |R R^T - I|`` may reach this (poses printed with 9 digits: about 1e-6)
ORTHONORMAL_TOLERANCE = 1e-3
#: bytes per point of a scan: float32 x, y, z, reflectance
POINT_BYTES = 16
_SCAN_NAME = "{:06d}.bin"


@dataclass(frozen=True)
class Sequence:
    """One drive of a dataset in this layout, checked whole (:func:`read_sequence`).

    poses: (N, 4, 4) float64 LiDAR-to-world, world = the LiDAR frame of the first scan; times: (N,)
    seconds, or None without ``times.txt``; scans: the N scan files, scan k first-to-last.
    """

    root: Path
    name: str
    scans: tuple[Path, ...]
    poses: np.ndarray
    times: np.ndarray | None
    #: the text files the poses came from (calib.txt, poses.txt and times.txt when present)
    meta_files: tuple[Path, ...]

    def __len__(self) -> int:
        return len(self.scans)

    @property
    def folder(self) -> Path:
        return self.root / "sequences" / self.name

    def points(self, k: int) -> np.ndarray:
        """(N, 4) float32 ``[x, y, z, reflectance]`` of scan ``k``, the LiDAR's frame."""
        return read_scan(self.scans[k])


def list_sequences(root: str | os.PathLike) -> list[str]:
    """The names of the sequences under ``<root>/sequences/`` that hold a ``velodyne/`` folder, sorted."""
    base = Path(root) / "sequences"
    if not base.is_dir():
        return []
    return sorted(p.name for p in base.iterdir() if (p / "velodyne").is_dir())


def read_sequence(root: str | os.PathLike, sequence: str) -> Sequence:
    """Sequence ``sequence`` of the dataset at ``root``, every file checked (module doc) before a
    point is read; the scans' sizes are checked, their points are read by :meth:`Sequence.points`."""
    root = Path(root)
    folder = root / "sequences" / sequence
    velodyne = folder / "velodyne"
    if not velodyne.is_dir():
        raise TypError(root, "sequence", f"a sequence of {root / 'sequences'} with a velodyne/ folder "
                       f"(found: {list_sequences(root) or 'none'})", sequence)
    scans = _scans(root, velodyne)
    tr = read_lidar_to_camera(root, folder / "calib.txt")
    poses_file = folder / "poses.txt"
    if not poses_file.exists() and (root / "poses" / f"{sequence}.txt").exists():
        poses_file = root / "poses" / f"{sequence}.txt"
    camera = read_poses(root, poses_file, len(scans))
    meta = [folder / "calib.txt", poses_file]
    times = None
    if (folder / "times.txt").exists():
        times = read_times(root, folder / "times.txt", len(scans))
        meta.append(folder / "times.txt")
    lidar = camera @ tr
    # camera 0's world has y down; the first scan's LiDAR frame has z up, as every pose typ writes
    return Sequence(root, sequence, scans, np.linalg.inv(lidar[0]) @ lidar, times, tuple(meta))


def read_scan(path: str | os.PathLike) -> np.ndarray:
    """(N, 4) float32 of one scan (:func:`typ.formats.binfile.read_bin`: finite, plausible metres)."""
    return read_bin(path, 4)


def _scans(root: Path, velodyne: Path) -> tuple[Path, ...]:
    names = sorted(p.name for p in velodyne.iterdir() if p.name.endswith(".bin"))
    if not names:
        raise TypError(velodyne, "scans", "NNNNNN.bin scans (float32 x, y, z, reflectance)", "none")
    expected = [_SCAN_NAME.format(k) for k in range(len(names))]
    if names != expected:
        odd = next(n for n, e in zip(names, expected) if n != e)
        raise TypError(velodyne, "scans", f"scans numbered from 000000.bin without gaps (scan k is the pose on "
                       f"line k + 1), {expected[0]} .. {expected[-1]}",
                       f"{odd} where {expected[names.index(odd)]} goes")
    scans = []
    for name in names:
        path = velodyne / name
        inside(path.relative_to(root), root, field="scan")
        try:
            size = path.stat().st_size
        except OSError as exc:
            raise TypError(path, "scan", "a readable scan file", f"{type(exc).__name__}: {exc.strerror}") from None
        if size == 0 or size % POINT_BYTES:
            raise TypError(path, "size", f"a positive multiple of {POINT_BYTES} bytes (float32 x, y, z, reflectance "
                           "per point); the file is truncated or has another column count",
                           f"{size} bytes ({size % POINT_BYTES} left over)")
        scans.append(path)
    return tuple(scans)


def _text_lines(root: Path, path: Path, noun: str) -> list[str]:
    inside(path.relative_to(root), root, field=noun)
    return read_text(path, noun, max_bytes=MAX_TEXT_BYTES, encoding="ascii").splitlines()


def _numbers(path: Path, number: int, tokens: list[str], count: int, what: str) -> np.ndarray:
    """``count`` finite float64 numbers parsed from ``tokens`` (line ``number`` of ``path``)."""
    if len(tokens) != count:
        raise TypError(path, f"line {number}", f"{count} numbers ({what})", f"{len(tokens)} fields")
    try:
        values = np.array([float(t) for t in tokens], dtype=np.float64)
    except ValueError:
        raise TypError(path, f"line {number}", f"{count} numbers ({what})", " ".join(tokens)[:80]) from None
    if not np.isfinite(values).all():
        raise TypError(path, f"line {number}", f"{count} finite numbers ({what})", " ".join(tokens)[:80])
    return values


def _rigid(path: Path, field: str, values: np.ndarray) -> np.ndarray:
    """The 4x4 matrix of a 3x4 row-major pose whose rotation is orthonormal with det +1."""
    m = np.eye(4)
    m[:3] = values.reshape(3, 4)
    rot = m[:3, :3]
    error = float(np.abs(rot @ rot.T - np.eye(3)).max())
    if error > ORTHONORMAL_TOLERANCE or abs(np.linalg.det(rot) - 1.0) > ORTHONORMAL_TOLERANCE:
        raise TypError(path, field, f"a rotation with |R R^T - I| <= {ORTHONORMAL_TOLERANCE:g} and det R = +1",
                       f"|R R^T - I| = {error:.3g}, det R = {np.linalg.det(rot):.3g}")
    return m


def read_lidar_to_camera(root: Path, path: Path) -> np.ndarray:
    """(4, 4) float64 ``Tr`` of a sequence's ``calib.txt``: the LiDAR frame into camera 0's."""
    for number, line in enumerate(_text_lines(root, path, "calib.txt"), start=1):
        key, sep, rest = line.partition(":")
        if sep and key.strip() == "Tr":
            return _rigid(path, f"line {number} (Tr)", _numbers(path, number, rest.split(), 12, "Tr, 3x4 row-major"))
    raise TypError(path, "Tr", "a line 'Tr: ' with 12 numbers (LiDAR -> camera 0, 3x4 row-major)", "missing")


def read_poses(root: Path, path: Path, scans: int) -> np.ndarray:
    """(N, 4, 4) float64 poses of ``poses.txt``, one line per scan (``scans`` of them)."""
    if not path.exists():
        raise TypError(path, "poses", f"one 3x4 pose per scan ({scans} lines; or poses/<seq>.txt under the root)",
                       "no such file")
    lines = [(n, line) for n, line in enumerate(_text_lines(root, path, "poses.txt"), start=1) if line.strip()]
    if len(lines) != scans:
        raise TypError(path, f"line {min(len(lines), scans) + 1}", f"one pose line per scan ({scans} scans in "
                       f"velodyne/)", f"{len(lines)} pose lines")
    return np.stack([_rigid(path, f"line {n}", _numbers(path, n, line.split(), 12, "a 3x4 row-major pose"))
                     for n, line in lines])


def read_times(root: Path, path: Path, scans: int) -> np.ndarray:
    """(N,) float64 seconds of ``times.txt``, one per scan, finite and never going back."""
    lines = [(n, line) for n, line in enumerate(_text_lines(root, path, "times.txt"), start=1) if line.strip()]
    if len(lines) != scans:
        raise TypError(path, f"line {min(len(lines), scans) + 1}", f"one time per scan ({scans} scans in velodyne/)",
                       f"{len(lines)} time lines")
    times = np.array([_numbers(path, n, line.split(), 1, "seconds")[0] for n, line in lines])
    back = np.flatnonzero(np.diff(times) < 0)
    if len(back):
        n = lines[back[0] + 1][0]
        raise TypError(path, f"line {n}", "times that never go back", f"{times[back[0] + 1]} after {times[back[0]]}")
    return times


#: the estimator counts points within this many degrees of a preset's beams (a drive's own
#: calibration puts half of KITTI's and nuScenes' returns within 0.05 deg of the presets, 0.6-0.7 within this)
ESTIMATE_TOLERANCE_DEG = 0.1
#: ... and takes the best preset when its share is at least this, and this many times the runner-up's
ESTIMATE_MIN_SHARE, ESTIMATE_MARGIN = 0.5, 1.25


def estimate_sensor(points: np.ndarray, *, where: str | os.PathLike = "scan") -> tuple[str, dict[str, float]]:
    """(the preset whose beams hold most of a scan's points, each preset's share): the real
    datasets' presets (:data:`typ.sensors.presets.PRESETS`), the share of the points at least 3 m
    away within :data:`ESTIMATE_TOLERANCE_DEG` of one of its beams. Neither clear enough (module
    constants) raises TypError asking for ``--sensor``."""
    from typ.sensors import on_beam_fractions
    from typ.sensors.presets import PRESETS

    shares = {name: on_beam_fractions(points, spec, (ESTIMATE_TOLERANCE_DEG,), min_range=3.0)[ESTIMATE_TOLERANCE_DEG]
              for name, spec in PRESETS.items()}
    ranked = sorted(shares, key=lambda n: -np.nan_to_num(shares[n]))
    best, second = shares[ranked[0]], shares[ranked[1]]
    if not (best >= ESTIMATE_MIN_SHARE and best >= ESTIMATE_MARGIN * second):
        raise TypError(where, "--sensor / sensor", "a LiDAR preset naming the drive's sensor (its scans match none "
                       "clearly)", {k: round(float(v), 3) for k, v in shares.items()})
    return ranked[0], shares
