"""Bad-input cases: the per-scene Parquet voxel store (registered with :func:`bad_inputs.make_corpus.case`)."""
from __future__ import annotations

import struct

import numpy as np

from typ.store import read_scene_voxels, scene_path, stored_grid, stored_input_hash, write_scene_voxels

from bad_inputs.make_corpus import GRID, Probe, case, forged_store, store_file, store_records, write


@case("store", "not_parquet", "wrong dtype")
def _(d):
    p = write(d / "s.parquet", "scene,agent\ns,1\n")
    return Probe(says=(str(p), "file", "a Parquet file written by typ.store"), call=lambda: read_scene_voxels(p))


@case("store", "empty_file", "empty")
def _(d):
    p = write(d / "s.parquet", b"")
    return Probe(says=(str(p), "file", "a Parquet file written by typ.store"), call=lambda: stored_input_hash(p))


@case("store", "footer_cut", "truncated")
def _(d):
    p = store_file(d / "s.parquet")
    p.write_bytes(p.read_bytes()[:-9])
    return Probe(says=(str(p), "file", "a Parquet file written by typ.store"), call=lambda: read_scene_voxels(p))


@case("store", "huge_footer_length", "huge")
def _(d):
    p = store_file(d / "s.parquet")
    raw = p.read_bytes()
    p.write_bytes(raw[:-8] + struct.pack("<I", 2**31 - 1) + raw[-4:])
    return Probe(says=(str(p), "file", "a Parquet file written by typ.store"), call=lambda: read_scene_voxels(p))


@case("store", "data_page_byte_flipped", "corrupt crc")
def _(d):
    import pyarrow.parquet as pq

    p = store_file(d / "s.parquet")
    raw, good = p.read_bytes(), pq.read_table(p)
    chunk = pq.ParquetFile(p).metadata.row_group(0).column(3)  # occ_ix's values
    # the first flip that Parquet alone reads back without complaint, as other voxel indices:
    # only the page CRC can tell
    for pos in range(chunk.data_page_offset, chunk.data_page_offset + chunk.total_compressed_size):
        flipped = bytearray(raw)
        flipped[pos] ^= 0x04
        p.write_bytes(bytes(flipped))
        try:
            if not pq.read_table(p).equals(good):
                break
        except Exception:  # noqa: BLE001 - this flip is caught by Parquet itself; look further
            continue
    return Probe(says=(str(p), "file", "a readable Parquet file written by typ.store"),
                 call=lambda: read_scene_voxels(p))


@case("store", "foreign_parquet", "missing keys")
def _(d):
    p = forged_store(d / "s.parquet", drop_meta=True)
    return Probe(says=(str(p), "schema metadata", "typ.voxel_store", "missing"), call=lambda: stored_input_hash(p))


@case("store", "future_version", "unknown")
def _(d):
    p = forged_store(d / "s.parquet", {"version": 99})
    return Probe(says=(str(p), "schema metadata", "version 1"), call=lambda: stored_input_hash(p))


@case("store", "grid_without_shape", "missing keys")
def _(d):
    grid = GRID.to_dict()
    del grid["shape"]
    p = forged_store(d / "s.parquet", {"grid": grid})
    return Probe(says=(str(p), "grid", "exactly the keys"), call=lambda: stored_grid(p))


@case("store", "index_outside_grid", "huge")
def _(d):
    p = forged_store(d / "s.parquet", occ_ix=40)
    return Probe(says=(str(p), "occ_ix", "indices < 16"), call=lambda: read_scene_voxels(p))


@case("store", "missing_file", "missing keys")
def _(d):
    p = d / "s.parquet"
    return Probe(says=(str(p), "file", "an existing voxel store file", "missing"), call=lambda: read_scene_voxels(p))


@case("store", "rewrite_with_float_occupancy_keeps_old_file", "wrong dtype")
def _(d):
    p = store_file(d / "s.parquet")
    records = {k: (v[0].astype(np.float32), v[1]) for k, v in store_records().items()}
    return Probe(says=(str(p), "occupancy", "(16, 16, 4) bool", "float32"),
                 call=lambda: write_scene_voxels(p, records, grid=GRID, input_hash="new"))


@case("store", "rewrite_with_wrong_grid_shape_keeps_old_file", "misaligned")
def _(d):
    p = store_file(d / "s.parquet")
    records = {("1", "0"): (np.zeros((16, 16, 5), bool), np.zeros((16, 16, 1), bool))}
    return Probe(says=(str(p), "occupancy", "(16, 16, 4) bool"),
                 call=lambda: write_scene_voxels(p, records, grid=GRID, input_hash="new"))


@case("store", "scene_name_escapes_root", "unknown")
def _(d):
    return Probe(says=(str(d), "scene", "a non-empty name of letters"),
                 call=lambda: scene_path(d, "target", "train", "../x"))
