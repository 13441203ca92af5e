"""Bad-input cases: KITTI object frames (velodyne, calib, label_2) (registered with :func:`bad_inputs.make_corpus.case`)."""
from __future__ import annotations

from pathlib import Path

from typ.formats.kitti import read_calib, read_kitti_frame, read_labels

from bad_inputs.make_corpus import CALIB, LABEL, Probe, case, kitti_frame, write


@case("kitti", "calib_r0_rect_missing", "missing keys")
def _(d):
    p = write(d / "calib.txt", "\n".join(l for l in CALIB.splitlines() if not l.startswith("R0_rect")))
    return Probe(says=(str(p), "R0_rect", "with 9 numbers", "missing"), call=lambda: read_calib(p))


@case("kitti", "calib_11_numbers", "misaligned")
def _(d):
    p = write(d / "calib.txt", CALIB.replace(" -3.32e-01", ""))
    return Probe(says=(str(p), "Tr_velo_to_cam", "12 numbers"), call=lambda: read_calib(p))


@case("kitti", "calib_nan", "nan/inf")
def _(d):
    p = write(d / "calib.txt", CALIB.replace("9.999e-01 1.009e-02", "nan 1.009e-02"))
    return Probe(says=(str(p), "R0_rect", "finite numbers"), call=lambda: read_calib(p))


@case("kitti", "calib_no_colon", "wrong dtype")
def _(d):
    p = write(d / "calib.txt", CALIB.replace("R0_rect:", "R0_rect"))
    return Probe(says=(str(p), "line 2", "'NAME: v1 v2 ...'"), call=lambda: read_calib(p))


def _labels(d: Path, text: str) -> Probe:
    p = write(d / "label.txt", text)
    calib = read_calib(write(d / "calib.txt", CALIB))
    return Probe(says=(str(p), "line 1"), call=lambda: read_labels(p, calib))


@case("kitti", "label_14_fields", "truncated")
def _(d):
    probe = _labels(d, LABEL.replace(" 1.57\n", "\n", 1))
    probe.says += ("15 fields",)
    return probe


@case("kitti", "label_non_numeric", "wrong dtype")
def _(d):
    probe = _labels(d, LABEL.replace("1.67 1.87 3.69", "1.67 wide 3.69"))
    probe.says += ("numbers in fields 9-15",)
    return probe


@case("kitti", "label_zero_height", "wrong units")
def _(d):
    probe = _labels(d, LABEL.replace("1.67 1.87 3.69", "0 1.87 3.69"))
    probe.says += ("positive h, w, l",)
    return probe


@case("kitti", "label_centimetres", "wrong units")
def _(d):
    probe = _labels(d, LABEL.replace("1.67 1.87 3.69", "167 187 369"))
    probe.says += ("h, w, l <= 100 m",)
    return probe


@case("kitti", "label_nan_location", "nan/inf")
def _(d):
    probe = _labels(d, LABEL.replace("-16.53 2.39 58.49", "nan 2.39 58.49"))
    probe.says += ("finite",)
    return probe


@case("kitti", "frame_without_velodyne", "missing keys")
def _(d):
    root = kitti_frame(d)
    (root / "training" / "velodyne" / "000000.bin").unlink()
    return Probe(says=(str(root / "training"), "velodyne", "000000.bin"), call=lambda: read_kitti_frame(root, 0))


@case("kitti", "labels_without_calib", "missing keys")
def _(d):
    root = kitti_frame(d, calib=None)
    calib = root / "training" / "calib" / "000000.txt"
    return Probe(says=(str(calib), "file", "an existing KITTI calib file"), call=lambda: read_kitti_frame(root, 0))


@case("kitti", "velodyne_truncated", "truncated")
def _(d):
    root = kitti_frame(d)
    velo = root / "training" / "velodyne" / "000000.bin"
    velo.write_bytes(velo.read_bytes()[:-5])
    return Probe(says=(str(velo), "size", "a multiple of 16 bytes"), call=lambda: read_kitti_frame(root, 0))
