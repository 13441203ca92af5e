"""Bad-input cases: drives in the KITTI odometry layout (``kitti-odometry``, registered with
:func:`bad_inputs.make_corpus.case`).

Each case writes a valid three-scan drive (``sequences/00/velodyne/00000k.bin``, ``calib.txt``
with ``Tr``, ``poses.txt``) and breaks one thing: the issue's classes (pose lines that are not one
per scan, a non-finite pose, a rotation that is not orthonormal, no ``Tr``, a scan whose size is no
multiple of 16 bytes) and a scan linked from outside the root. The error must name the file and
the line, and ``typ novel-view`` must write nothing.
"""
from __future__ import annotations

from pathlib import Path

from bad_inputs.make_corpus import Probe, case, cloud, write
from tasks.ingest import list_dataset
from typ.formats.kitti_odometry import read_sequence

#: KITTI seq 00's Tr (LiDAR -> camera 0), as its calib.txt prints it
TR = ("4.276802385584e-04 -9.999672484946e-01 -8.084491683471e-03 -1.198459927713e-02 -7.210626507497e-03 "
      "8.081198471645e-03 -9.999413164504e-01 -5.403984729748e-02 9.999738645903e-01 4.859485810390e-04 "
      "-7.206933692422e-03 -2.921968648686e-01")
#: camera 0 moving 5 m forward (its z) per scan
POSES = [f"1 0 0 0 0 1 0 0 0 0 1 {5.0 * k:.1f}" for k in range(3)]


def drive(d: Path, *, poses: list[str] = POSES, calib: str = f"P0: 1 0 0 0 0 1 0 0 0 0 1 0\nTr: {TR}\n",
          scans: int = 3) -> Path:
    """A valid drive under ``d/data`` (its root), three scans of 64 points unless told otherwise."""
    root = d / "data"
    seq = root / "sequences" / "00"
    for k in range(scans):
        write(seq / "velodyne" / f"{k:06d}.bin", cloud(seed=k).tobytes())
    write(seq / "calib.txt", calib)
    write(seq / "poses.txt", "".join(f"{line}\n" for line in poses))
    return root


def listed(root: Path, *says: str) -> Probe:
    """What ``simulate.sources`` and ``typ generate`` list (:func:`tasks.ingest.list_dataset`) refused."""
    return Probe(says=says, call=lambda: list_dataset("kitti-odometry", root, sensor="kitti"))


@case("kitti-odometry", "fewer_pose_lines_than_scans", "truncated")
def _(d):
    root = drive(d, poses=POSES[:2])
    return listed(root, str(root / "sequences" / "00" / "poses.txt"), "line 3", "one pose line per scan")


@case("kitti-odometry", "pose_with_nan", "nan/inf")
def _(d):
    root = drive(d, poses=[POSES[0], "1 0 0 nan 0 1 0 0 0 0 1 5", POSES[2]])
    return listed(root, str(root / "sequences" / "00" / "poses.txt"), "line 2", "finite numbers")


@case("kitti-odometry", "rotation_not_orthonormal", "wrong units")
def _(d):
    root = drive(d, poses=[POSES[0], POSES[1], "1 0 0 0 0 1 0.2 0 0 0 1 10"])
    return Probe(says=(str(root / "sequences" / "00" / "poses.txt"), "line 3", "R R^T - I"),
                 call=lambda: read_sequence(root, "00"))


@case("kitti-odometry", "calib_without_tr", "missing keys")
def _(d):
    root = drive(d, calib="P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    return listed(root, str(root / "sequences" / "00" / "calib.txt"), "Tr", "LiDAR -> camera 0")


@case("kitti-odometry", "scan_not_whole_points", "misaligned")
def _(d):
    root = drive(d)
    scan = root / "sequences" / "00" / "velodyne" / "000001.bin"
    scan.write_bytes(scan.read_bytes() + bytes(12))
    return listed(root, str(scan), "size", "multiple of 16 bytes")


@case("kitti-odometry", "scan_linked_from_outside", "link")
def _(d):
    root = drive(d)
    outside = write(d / "outside" / "000002.bin", cloud(seed=9).tobytes())
    scan = root / "sequences" / "00" / "velodyne" / "000002.bin"
    scan.unlink()
    scan.symlink_to(outside)
    return listed(root, str(scan), "a path inside")


@case("kitti-odometry", "novel_view_with_a_pose_short", "truncated")
def _(d):
    root = drive(d, poses=POSES[:2])
    out = d / "out"
    write(out / "novel_view.md", "an earlier report\n")
    repo = Path(__file__).resolve().parents[3]
    return Probe(says=(str(root / "sequences" / "00" / "poses.txt"), "line 3", "one pose line per scan"),
                 argv=["--root", str(repo), "novel-view", "--format", "kitti-odometry", "--input", str(root),
                       "--out", str(out), "--methods", "copy"], watch=d)
