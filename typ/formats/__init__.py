"""Readers and writers of LiDAR datasets' on-disk formats, all returning :class:`typ.scene.Scene`.

- :mod:`.opv2v`: OPV2V / V2V4Real scenario folders (pcd + yaml), read and write.
- :mod:`.kitti`: KITTI 3D object frames.
- :mod:`.nuscenes`: nuScenes keyframes with mmdet3d info JSON.
- :mod:`.waymo`: Waymo Open Dataset tfrecords (no TensorFlow) and mmdet3d's Waymo bins.
- :mod:`.pcd`, :mod:`.binfile`: the point cloud files underneath.

Every bad input raises :class:`typ.errors.TypError` naming the file and the field.
"""
from typ.formats.binfile import read_bin
from typ.formats.kitti import read_calib, read_kitti_frame, read_labels
from typ.formats.nuscenes import read_nuscenes_frame
from typ.formats.opv2v import list_agents, list_scenarios, list_timestamps, read_meta, read_scene, write_scene
from typ.formats.pcd import read_pcd, write_pcd
from typ.formats.waymo import (crc32c, iter_tfrecord, iter_waymo_frames, masked_crc32c, read_waymo_frames,
                               read_waymo_kitti_bin)

__all__ = [
    "crc32c", "iter_tfrecord", "list_agents", "list_scenarios", "list_timestamps", "masked_crc32c",
    "read_bin", "read_calib", "read_kitti_frame", "read_labels", "read_meta", "read_nuscenes_frame",
    "read_pcd", "read_scene", "iter_waymo_frames", "read_waymo_frames", "read_waymo_kitti_bin", "write_pcd", "write_scene",
]
