"""Single-agent frames from KITTI, nuScenes or Waymo as OPV2V-layout scenarios: what ``typ generate
--format`` generates from, and a domain ``simulate`` takes from a real dataset (``simulate.sources``).

A dataset is listed as :class:`DatasetScenario` s before anything is read: a KITTI frame stands
alone; a nuScenes scene (the info records sharing a ``scene_token``, in time order) is one
scenario, a keyframe without one stands alone; a Waymo segment (one tfrecord) is one scenario,
read and written one frame at a time; a drive in the KITTI odometry layout (``kitti-odometry``) is
one scenario with one frame per scan and the scans' poses (a range of its frames, with
``frame_ranges``). Each frame is moved into its LiDAR's sensor frame when
the dataset reports points in a vehicle frame (Waymo: origin on the ground, so the grid's z
range, which is relative to the sensor, would miss most points) and written with
:func:`typ.formats.opv2v.write_scene`, the ego's yaml naming its LiDAR (``sensor: kitti``) so
that the stages after find the dataset's mount height in :mod:`typ.sensors`.

The dataset's own splits (KITTI ``ImageSets/*.txt`` and ``training``/``testing``; Waymo
``training``/``validation``/``testing`` folders; nuScenes info files ``*_train``/``*_val``/
``*_test``) become typ's as ``SourceConfig.splits`` maps them (:func:`assign_splits`); a dataset
without any is shared out by a hash of each scenario's name (:data:`DEFAULT_FRACTIONS`).
"""
from __future__ import annotations

import dataclasses
import hashlib
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

from typ import registry
from typ.config import SourceConfig
from typ.errors import TypError
from typ.formats.kitti import MAX_TEXT_BYTES, read_kitti_frame
from typ.formats.kitti_odometry import estimate_sensor, list_sequences, read_sequence
from typ.formats.nuscenes import read_info, record_frame
from typ.formats.opv2v import time_order, write_scene
from typ.formats.waymo import iter_waymo_frames
from typ.inputs import inside, read_text
from typ.io import atomic_path, code_digest, hash_files, hash_obj, write_manifest
from typ.registry import ReaderSpec
from typ.scene import AgentView, Scene
from typ.sensors import resolve
import typ.formats
import typ.scene
import typ.sensors.presets

#: what the manifest of a scenario written here names as its writer (typ.io.write_manifest)
STAGE = "ingest"
#: typ split -> the dataset's split names it takes when ``splits`` is not given, the first found
SPLIT_NAMES = {"train": ("train", "training"), "val": ("val", "validation"), "test": ("test", "testing"),
               "pretrain": ("pretrain",)}
#: a dataset without splits of its own: the fraction of its scenarios each typ split takes
DEFAULT_FRACTIONS = {"train": 0.7, "val": 0.1, "test": 0.1, "pretrain": 0.1}
#: drives in the KITTI odometry / SemanticKITTI layout (typ.formats.kitti_odometry)
ODOMETRY = "kitti-odometry"
#: what decides how a dataset's frames are read and written: a change redoes every scenario
_CODE = code_digest(typ.formats, typ.scene, typ.sensors.presets, sys.modules[__name__])


@dataclass(frozen=True)
class DatasetScenario:
    """One scenario of a single-agent dataset before it is read: iterating it reads its frames in
    time order, each in its LiDAR's sensor frame, one at a time (a Waymo segment is about 1 GB)."""

    fmt: str
    name: str
    #: the files it is read from, in reading order (the scenario's key hashes them)
    files: tuple[Path, ...]
    #: kitti: ((root, split folder, frame id),); nuscenes: ((record, categories, bin, info), ...) in
    #: time order; waymo: (); kitti-odometry: ((Sequence, first scan, stop),)
    parts: tuple = field(default=(), compare=False, hash=False)
    #: the preset of its LiDAR (typ.sensors) the written yaml names; empty: the format's own
    sensor: str = ""

    @property
    def lidar(self) -> str:
        """The LiDAR preset its frames are scans of."""
        return self.sensor or READERS[self.fmt].preset

    def __iter__(self) -> Iterator[Scene]:
        reader = READERS[self.fmt]
        lift = reader.lift(self.lidar)
        for stamp, scene in enumerate(reader.frames(self)):
            scene = to_sensor_frame(scene, lift)
            # stamps that are not the files' order (nuScenes, KITTI): number the frames as they come
            yield dataclasses.replace(scene, scenario=self.name,
                                      timestamp=scene.timestamp if reader.spec.own_timestamps else f"{stamp:06d}")

    def key(self) -> str:
        """A digest of everything the scenario's files hold and how they are read."""
        records = [part[0] for part in self.parts] if READERS[self.fmt].spec.keyed_records else []
        return hash_files(self.files, extra=hash_obj({"name": self.name, "format": self.fmt, "records": records,
                                                      "code": _CODE, "sensor": self.lidar,
                                                      "frames": [list(p[1:]) for p in self.parts]
                                                      if self.fmt == ODOMETRY else []}))


def list_dataset(fmt: str, root: str | Path, *, sensor: str | None = None
                 ) -> tuple[list[DatasetScenario], dict[str, list[str]]]:
    """(the scenarios of the ``fmt`` dataset at ``root``, sorted by name; the dataset's own splits,
    name -> scenario names). Raises TypError for an unknown format, a root that is no folder or
    holds no frame, a split file naming a frame the root lacks, a nuScenes record whose point
    cloud is missing, a file or folder that leads out of the root (an absolute or climbing
    ``lidar_path``, a link elsewhere: :func:`typ.inputs.inside`, checked before it is read), and two
    scenarios of one name.

    sensor: the preset (:data:`typ.sensors.SENSORS`) its scans are of; unset, the format's own
    (``kitti-odometry``: estimated from each drive's first scan, :func:`typ.formats.kitti_odometry.estimate_sensor`).

    kitti: ``training/`` and ``testing/`` (velodyne or velodyne_reduced, label_2, calib), splits
    ``training``, ``testing`` and each ``ImageSets/<name>.txt`` (frame ids; ``test`` in testing/).
    nuscenes: mmdet3d info JSONs (``*info*.json``) beside their point clouds (``lidar_path``
    relative to the root, or in ``samples/LIDAR_TOP/`` or the root itself); a file named
    ``*_train``, ``*_val`` or ``*_test`` is that split.
    waymo: ``*.tfrecord`` segments in the root (no split) and in ``training/``, ``validation/``,
    ``testing/``. kitti-odometry: ``sequences/<seq>/`` with ``velodyne/*.bin``, ``calib.txt`` and
    ``poses.txt``, each sequence checked whole (:func:`typ.formats.kitti_odometry.read_sequence`).
    """
    root = Path(root)
    if fmt not in FORMATS:
        raise TypError(root, "format", f"one of {list(FORMATS)}", fmt)
    if not root.is_dir():
        raise TypError(root, "root", f"a {fmt} dataset folder", "not a folder")
    if sensor is not None:
        resolve(sensor, where="typ", field="--sensor / sensor")
    scenarios, splits = READERS[fmt].find(root)
    scenarios = [READERS[fmt].scenario(s) for s in scenarios]
    if not scenarios:
        raise TypError(root, "root", f"{fmt} frames ({READERS[fmt].spec.layout})", "none found")
    if sensor is not None or READERS[fmt].estimate is not None:
        scenarios = [dataclasses.replace(s, sensor=sensor or READERS[fmt].estimate(s)) for s in scenarios]
    by_name: dict[str, DatasetScenario] = {}
    for scenario in scenarios:
        if scenario.name in by_name:
            raise TypError(root, "scenario", "one scenario per name", f"{scenario.name} from {scenario.files[0]} "
                           f"and {by_name[scenario.name].files[0]}")
        by_name[scenario.name] = scenario
    return sorted(scenarios, key=lambda s: s.name), {k: sorted(v) for k, v in splits.items() if v}



def find_kitti(root: Path) -> tuple[list[DatasetScenario], dict[str, list[str]]]:
    scenarios, splits, names = [], {}, {}
    for folder in ("training", "testing"):
        base = root / folder
        frames = sorted({p.stem for sub in ("velodyne", "velodyne_reduced") for p in (base / sub).glob("*.bin")})
        names[folder] = {frame: _safe(f"kitti_{folder}_{frame}") for frame in frames}
        splits[folder] = list(names[folder].values())
        for frame in frames:
            cloud = next(p for p in (base / "velodyne" / f"{frame}.bin", base / "velodyne_reduced" / f"{frame}.bin")
                         if p.exists())
            labelled = (base / "label_2").is_dir()
            files = [cloud] + ([base / "calib" / f"{frame}.txt", base / "label_2" / f"{frame}.txt"] if labelled else [])
            # the scenario's key reads these files: each must lie inside the root before it is hashed
            files = [inside(p.relative_to(root), root) for p in files]
            scenarios.append(DatasetScenario("kitti", names[folder][frame], tuple(p for p in files if p.is_file()),
                                             ((root, folder, frame),)))
    for split_file in sorted(inside(p.relative_to(root), root) for p in (root / "ImageSets").glob("*.txt")):
        folder = "testing" if split_file.stem == "test" else "training"
        lines = read_text(split_file, "KITTI split file", max_bytes=MAX_TEXT_BYTES, encoding="ascii").splitlines()
        members = []
        for number, line in enumerate(lines, start=1):
            frame = line.strip()
            if not frame:
                continue
            if frame not in names[folder]:
                raise TypError(split_file, f"line {number}", f"a frame id of {folder}/velodyne (a .bin there)",
                               frame[:80])
            members.append(names[folder][frame])
        splits[split_file.stem] = members
    return scenarios, splits


def find_nuscenes(root: Path) -> tuple[list[DatasetScenario], dict[str, list[str]]]:
    scenarios, splits = [], {}
    for info_path in sorted(inside(p.name, root) for p in root.glob("*.json") if "info" in p.name):
        records, categories = read_info(info_path)
        scenes: dict[str, list] = {}
        for k, record in enumerate(records):
            token = record.get("scene_token")
            if token is not None and not (isinstance(token, str) and token):
                raise TypError(info_path, f"data_list[{k}].scene_token", "a scene token (a string)", token)
            bin_path = _record_cloud(root, info_path, k, record)
            name = _safe(f"nuscenes_{token}") if token else _safe(bin_path.name.split(".")[0])
            scenes.setdefault(name, []).append((_microseconds(info_path, k, record), record, bin_path))
        split = re.search(r"_(train|val|test)$", info_path.stem)
        for name, frames in scenes.items():
            frames.sort(key=lambda f: f[0])
            parts = tuple((record, categories, bin_path, info_path) for _, record, bin_path in frames)
            scenarios.append(DatasetScenario("nuscenes", name, tuple(p[2] for p in parts), parts))
            if split:
                splits.setdefault(split.group(1), []).append(name)
    return scenarios, splits


def _record_cloud(root: Path, info_path: Path, k: int, record: dict) -> Path:
    """The point cloud of info record ``k``: its lidar_path under the root, else that file name in
    ``samples/LIDAR_TOP/`` or the root (mmdet3d v1.x keeps the name only). Each of them must lead to a
    file inside the root (:func:`typ.inputs.inside`): an absolute or climbing lidar_path, or a link out
    of the root, is refused, never read."""
    lidar_path = record["lidar_points"]["lidar_path"]
    name = Path(lidar_path).name
    field = f"data_list[{k}].lidar_points.lidar_path"
    candidates = [inside(p, root, where=info_path, field=field)
                  for p in (lidar_path, Path("samples") / "LIDAR_TOP" / name, name)]
    found = next((p for p in candidates if p.is_file()), None)
    if found is None:
        raise TypError(info_path, f"data_list[{k}].lidar_points.lidar_path",
                       f"a point cloud file at one of {[str(p) for p in dict.fromkeys(candidates)]}",
                       f"{lidar_path!r}: not found")
    return found


def _microseconds(info_path: Path, k: int, record: dict) -> int:
    """A record's time in microseconds: mmdet3d v1.x writes seconds, the devkit microseconds."""
    t = record.get("timestamp")
    if isinstance(t, bool) or not isinstance(t, (int, float)) or not np.isfinite(t) or not 0 <= t < 2**62:
        raise TypError(info_path, f"data_list[{k}].timestamp", "a time in seconds or microseconds", t)
    return int(round(t * 1e6)) if t < 1e11 else int(t)


def find_waymo(root: Path) -> tuple[list[DatasetScenario], dict[str, list[str]]]:
    scenarios, splits = [], {}
    for folder in ("", "training", "validation", "testing"):
        for path in sorted((root / folder).glob("*.tfrecord")):
            scenarios.append(_file_scenario("waymo", inside(path.relative_to(root), root)))
            if folder:
                splits.setdefault(folder, []).append(scenarios[-1].name)
    return scenarios, splits


def find_kitti_odometry(root: Path) -> tuple[list[DatasetScenario], dict[str, list[str]]]:
    scenarios = []
    for name in list_sequences(root):
        sequence = read_sequence(root, name)
        scenarios.append(DatasetScenario(ODOMETRY, _safe(f"{root.resolve().name}_{name}"),
                                         (*sequence.meta_files, *sequence.scans), ((sequence, 0, len(sequence)),)))
    return scenarios, {}


def kitti_odometry_frames(scenario: DatasetScenario) -> Iterator[Scene]:
    (sequence, first, stop), = scenario.parts
    for k in range(first, stop):
        view = AgentView(agent_id="ego", points=sequence.points(k), pose=sequence.poses[k].copy(),
                         where=str(sequence.scans[k]))
        yield Scene(scenario=scenario.name, timestamp=f"{k:06d}", agents={"ego": view}, dataset=ODOMETRY)


def estimate_odometry_sensor(scenario: DatasetScenario) -> str:
    (sequence, first, _), = scenario.parts
    return estimate_sensor(sequence.points(first), where=sequence.scans[first])[0]


def _file_scenario(fmt: str, path: Path) -> DatasetScenario:
    """The scenario of a format whose one file is one scenario (a Waymo segment), named by the file."""
    return DatasetScenario(fmt, _safe(path.name.split(".")[0]), (path,))


def _safe(name: str) -> str:
    """A scenario folder name: letters, digits, ``_`` and ``-`` only, at most 80 characters."""
    return "".join(c if c.isalnum() or c in "_-" else "_" for c in name)[:80]


def kitti_frames(scenario: DatasetScenario) -> Iterator[Scene]:
    (root, folder, frame), = scenario.parts
    yield read_kitti_frame(root, frame, folder)


def nuscenes_frames(scenario: DatasetScenario) -> Iterator[Scene]:
    for record, categories, bin_path, info_path in scenario.parts:
        yield record_frame(record, categories, bin_path, info_path)


def waymo_frames(scenario: DatasetScenario) -> Iterator[Scene]:
    yield from iter_waymo_frames(scenario.files[0])


@dataclass(frozen=True)
class Reader:
    """One single-agent dataset format: its registry entry (:class:`typ.registry.ReaderSpec`: layout,
    frame conventions, LiDAR) with its functions resolved: ``find(root)`` -> (its scenarios, its own
    splits); ``frames(scenario)`` its frames in time order, one at a time; ``estimate(scenario)``
    the LiDAR preset a scenario's scans show (None: the preset ``spec.sensor`` names, or the one of
    the format's name); ``--sensor`` names another.

    A new format is one module ``typ/formats/<name>.py`` holding its frame reader and its ``find``
    (scenarios as ``(name, files, parts)`` tuples) and ``frames`` functions, and an entry in
    :data:`typ.registry.READERS` naming them (the config offers its name from there)."""

    name: str
    spec: ReaderSpec
    find: Callable[[Path], tuple[list[DatasetScenario], dict[str, list[str]]]]
    frames: Callable[[DatasetScenario], Iterator[Scene]]
    estimate: Callable[[DatasetScenario], str] | None = None

    @classmethod
    def of(cls, name: str, spec: ReaderSpec) -> "Reader":
        """The reader registry entry ``name`` describes."""
        return cls(name, spec, registry.load(spec.find), registry.load(spec.frames),
                   registry.load(spec.estimate) if spec.estimate else None)

    @property
    def preset(self) -> str:
        return self.spec.sensor or self.name

    def scenario(self, found) -> DatasetScenario:
        """One scenario ``find`` listed: a :class:`DatasetScenario`, or ``(name, files, parts)`` from
        a reader that lives below ``tasks/`` (a format module: ``typ/formats/<name>.py``)."""
        if isinstance(found, DatasetScenario):
            return found
        if not isinstance(found, tuple) or len(found) not in (2, 3) or not isinstance(found[0], str):
            raise TypError(self.spec.find, "scenario", "a DatasetScenario or a (name, files, parts) tuple",
                           type(found).__name__)
        return DatasetScenario(self.name, found[0], tuple(Path(f) for f in found[1]), *found[2:])

    def lift(self, lidar: str) -> float:
        """Height of ``lidar`` (a preset name) above the frame this format's points come in: its
        mount height for a vehicle-frame format, else 0 (the points are in the LiDAR's own frame).
        Looked up when a scenario is read, so a reader whose LiDAR is named per source (a preset
        not of its own name) imports and lists without one."""
        if not self.spec.vehicle_frame:
            return 0.0
        return resolve(lidar, where=f"the {self.name} reader (tasks/ingest.py)", field="sensor").mount_height


#: every single-agent format, by name (``simulate.sources.<domain>.format``, ``typ generate --format``):
#: :data:`typ.registry.READERS`, whose entries name the functions above
READERS: dict[str, Reader] = {name: Reader.of(name, spec) for name, spec in registry.READERS.items()}
FORMATS = tuple(READERS)


@dataclass(frozen=True)
class SplitShare:
    """Which scenarios of one dataset a typ split takes, and the rule, as the stage's metrics say it."""

    scenarios: list[DatasetScenario]
    rule: str


def assign_splits(fmt: str, listing: tuple[list[DatasetScenario], dict[str, list[str]]], splits: dict,
                  *, where: str, field: str) -> dict[str, SplitShare]:
    """typ split -> what it takes of a listed dataset (:func:`list_dataset`), by ``splits``
    (``SourceConfig.splits``; empty: :data:`SPLIT_NAMES`, or :data:`DEFAULT_FRACTIONS` for a
    dataset without splits of its own).

    A list names dataset splits taken whole. A fraction f takes the scenarios no list takes whose
    ``sha256(name)``, as a number in [0, 1), falls in the split's share: the fractions laid end to
    end in the order train, val, test, pretrain, then the others by name. A scenario in two typ
    splits, or a split name the dataset does not have, raises TypError naming ``<field>.splits``.
    """
    scenarios, own = listing
    if not splits:
        splits = ({split: [next(n for n in names if n in own)] for split, names in SPLIT_NAMES.items()
                   if any(n in own for n in names)} if own else dict(DEFAULT_FRACTIONS))
    by_name = {s.name: s for s in scenarios}
    shares: dict[str, SplitShare] = {}
    owner: dict[str, str] = {}
    for split, names in splits.items():
        if not isinstance(names, list):
            continue
        for n in names:
            if n not in own:
                raise TypError(where, f"{field}.splits.{split}", f"split names this {fmt} root has: {sorted(own)}", n)
        members = sorted({m for n in names for m in own[n]})
        for m in members:
            if owner.setdefault(m, split) != split:
                raise TypError(where, f"{field}.splits", "typ splits that share no scenario",
                               f"{m} in both {owner[m]} and {split}")
        shares[split] = SplitShare([by_name[m] for m in members], f"{fmt} split {' + '.join(names)}")
    order = {name: i for i, name in enumerate(SPLIT_NAMES)}
    fractions = sorted(((s, f) for s, f in splits.items() if not isinstance(f, list)),
                       key=lambda item: (order.get(item[0], len(order)), item[0]))
    pool = [s for s in scenarios if s.name not in owner]
    low = 0.0
    for split, fraction in fractions:
        high = low + fraction
        shares[split] = SplitShare([s for s in pool if low <= name_hash(s.name) < high],
                                   f"{fmt}: sha256(scenario name) in [{low:.3g}, {high:.3g}) of the "
                                   f"{len(pool)} scenarios no named split takes")
        low = high
    return shares


def name_hash(name: str) -> float:
    """A scenario name as a number in [0, 1): the first 8 bytes of its sha256, big-endian, over 2^64."""
    return int.from_bytes(hashlib.sha256(name.encode()).digest()[:8], "big") / 2.0**64


def source_splits(block: SourceConfig, data_root: Path, *, where: str, field: str) -> dict[str, SplitShare]:
    """typ split -> its share of the single-agent dataset ``block`` names (rooted at ``data_root``)."""
    listing = list_dataset(block.format, data_root, sensor=block.sensor or None)
    if block.frame_ranges:
        return frame_range_splits(listing[0], block.frame_ranges, where=where, field=field)
    return assign_splits(block.format, listing, block.splits, where=where, field=field)


def frame_range_splits(drives: list[DatasetScenario], ranges: dict, *, where: str, field: str) -> dict[str, SplitShare]:
    """typ split -> scans ``[first, stop)`` of every drive (``kitti-odometry`` scenarios), each range
    a scenario named ``<drive>_f<first>-<stop>``; a range past a drive's end raises TypError."""
    shares = {}
    for split, (first, stop) in ranges.items():
        taken = []
        for drive in drives:
            (sequence, _, end), = drive.parts
            if stop > end:
                raise TypError(where, f"{field}.frame_ranges.{split}", f"scans within the {end} of {drive.name}",
                               [first, stop])
            taken.append(dataclasses.replace(
                drive, name=_safe(f"{drive.name}_f{first}-{stop}"), parts=((sequence, first, stop),),
                files=(*sequence.meta_files, *sequence.scans[first:stop])))
        shares[split] = SplitShare(taken, f"{ODOMETRY}: scans [{first}, {stop}) of each drive (split by frame range)")
    return shares


@dataclass(frozen=True)
class IngestJob:
    """One scenario of a single-agent dataset, written as a one-agent OPV2V-layout scenario of a domain."""

    domain: str
    split: str
    scenario: DatasetScenario
    #: how the scenario came to this split (:attr:`SplitShare.rule`)
    rule: str = ""
    #: frames, views, points, boxes, from :meth:`check` when planned
    counts: dict = field(default_factory=dict, compare=False, hash=False)

    @property
    def name(self) -> str:
        return self.scenario.name

    def folder(self, out: Path) -> Path:
        return out / self.domain / self.split / self.name

    def key(self) -> str:
        return self.scenario.key()

    def describe(self) -> dict:
        return {"domain": self.domain, "split": self.split, "format": self.scenario.fmt, "rule": self.rule,
                "files": [str(p.resolve()) for p in self.scenario.files]}

    def check(self) -> dict:
        """Read every frame as :meth:`write` will, keeping none: the counts, or TypError naming the
        first bad file and field."""
        return frame_counts(self.scenario)

    def write(self, tmp: Path) -> dict:
        """Write the scenario's frames into ``tmp``; its counts."""
        return write_frames(self.scenario, tmp, sensor=self.scenario.lidar)


def frame_counts(frames: Iterable[Scene]) -> dict:
    """frames, views, points, boxes of a single-agent scenario, each frame checked as it is written:
    at least one frame, one frame per timestamp, object ids unique within a frame (one yaml entry
    per vehicle)."""
    counts = {"frames": 0, "views": 0, "points": 0, "boxes": 0}
    stamps = set()
    for scene in frames:
        _check_ids(scene)
        if scene.timestamp in stamps:
            raise TypError(scene.ego.where, "timestamp", "one frame per timestamp in a scenario", scene.timestamp)
        stamps.add(scene.timestamp)
        counts["frames"] += 1
        counts["views"] += 1
        counts["points"] += len(scene.ego.points)
        counts["boxes"] += len(scene.ego.boxes)
    if not counts["frames"]:
        raise TypError(getattr(frames, "name", "scenario"), "frames", "at least one frame", "none")
    return counts


def _check_ids(scene: Scene) -> None:
    ids = scene.ego.box_ids.tolist()
    if len(set(ids)) != len(ids):
        raise TypError(scene.ego.where, "box ids", "one id per labelled object",
                       sorted({i for i in ids if ids.count(i) > 1})[:5])


def read_frames(fmt: str, path: str | Path, *, sensor: str | None = None) -> list[DatasetScenario]:
    """``typ generate --format``'s scenarios: every scenario of the dataset at ``path``
    (:func:`list_dataset`; for waymo, ``path`` may also be one tfrecord); ``sensor``: ``--sensor``."""
    path = Path(path)
    if fmt not in FORMATS:
        raise TypError("typ generate", "--format", f"one of {list(FORMATS)}", fmt)
    if not path.exists():
        raise TypError(path, "--input", f"an existing {fmt} file or folder", "not found")
    if READERS[fmt].spec.one_file and path.is_file():
        scenario = _file_scenario(fmt, path)
        return [dataclasses.replace(scenario, sensor=sensor) if sensor else scenario]
    return list_dataset(fmt, path, sensor=sensor)[0]


def to_sensor_frame(scene: Scene, height: float) -> Scene:
    """Move the ego's points, boxes and pose from a vehicle frame to a sensor ``height`` m above it."""
    if height == 0.0:
        return scene
    ego = scene.ego
    lift = np.eye(4)
    lift[2, 3] = height
    points = ego.points.copy()
    points[:, 2] -= np.float32(height)
    boxes = ego.boxes.copy()
    boxes[:, 2] -= height
    view = dataclasses.replace(ego, points=points, boxes=boxes, pose=ego.pose @ lift)
    return dataclasses.replace(scene, agents={ego.agent_id: view})


def write_single_agent(scenarios: Iterable[DatasetScenario], root: Path, *, inside: Path | None = None) -> list[Path]:
    """Write every scenario as ``<root>/<scenario>/<agent>/<timestamp>.pcd|.yaml`` (:func:`write_frames`),
    each whole or not at all; returns the folders. ``inside``: the output folder ``root`` lies in
    (``root`` itself by default), which no write leaves through a link (:func:`typ.io.atomic_path`)."""
    folders = []
    for scenario in scenarios:
        target = root / scenario.name
        with atomic_path(target, stage=STAGE, inside=inside or root) as tmp:
            tmp.mkdir(parents=True)
            counts = write_frames(scenario, tmp, sensor=scenario.lidar)
            write_manifest(tmp, STAGE, {"frames": counts["frames"]})
        folders.append(target)
    return folders


def write_frames(frames: Iterable[Scene], folder: Path, *, sensor: str) -> dict:
    """Write a single-agent scenario's frames into ``folder`` as they come, the ego's yaml naming its
    LiDAR (``sensor``), numbered ``000000``, ``000001``, ... in time order; returns
    :func:`frame_counts`'s counts."""
    stamps = []

    def written() -> Iterator[Scene]:
        for scene in frames:
            write_scene(dataclasses.replace(scene, scenario=folder.name), folder,
                        meta={scene.ego_id: {"sensor": sensor}})
            stamps.append(scene.timestamp)
            yield scene

    counts = frame_counts(written())
    _number_in_time_order(folder, stamps)
    return counts


def _number_in_time_order(folder: Path, stamps: list[str]) -> None:
    """Rename each frame's files from its timestamp to its rank in time: OpenCOOD sorts timestamps
    as strings, and ``000010`` after ``000009`` keeps that order the time order."""
    if len(set(stamps)) != len(stamps):
        dup = next(t for t in stamps if stamps.count(t) > 1)
        raise TypError(folder.name, "timestamp", "one frame per timestamp in a scenario", dup)
    ranked = sorted(stamps, key=time_order)
    renames = {old: f"{i:06d}" for i, old in enumerate(ranked) if old != f"{i:06d}"}
    agents = [d for d in folder.iterdir() if d.is_dir()]
    for stage in ("tmp", "final"):   # through temporary names: a new name may be another frame's old one
        for old, new in renames.items():
            for agent in agents:
                for suffix in (".pcd", ".yaml"):
                    src = agent / (f"{old}{suffix}" if stage == "tmp" else f".rank-{new}{suffix}")
                    dst = agent / (f".rank-{new}{suffix}" if stage == "tmp" else f"{new}{suffix}")
                    if src.exists():
                        src.rename(dst)
