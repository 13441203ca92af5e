"""Bad-input cases: OPV2V scenarios (scenario/agent/timestamp.yaml + .pcd) (registered with :func:`bad_inputs.make_corpus.case`)."""
from __future__ import annotations

import yaml

from typ.formats.opv2v import list_agents, list_scenarios

from bad_inputs.make_corpus import Probe, _read_opv2v, case, opv2v_doc, opv2v_scenario, unreadable, write


@case("opv2v", "yaml_not_yaml", "wrong dtype")
def _(d):
    y = opv2v_scenario(d, "lidar_pose: [1, 2\nvehicles: {}\n")
    return Probe(says=(str(y), "yaml", "well-formed YAML", "line"), call=_read_opv2v(y))


@case("opv2v", "yaml_empty", "empty")
def _(d):
    y = opv2v_scenario(d, "")
    return Probe(says=(str(y), "yaml", "a mapping with lidar_pose and vehicles"), call=_read_opv2v(y))


@case("opv2v", "yaml_truncated", "truncated")
def _(d):
    text = yaml.safe_dump(opv2v_doc())
    y = opv2v_scenario(d, text[: text.index("vehicles")])  # cut before the vehicles block
    return Probe(says=(str(y), "vehicles", "a mapping of vehicle id"), call=_read_opv2v(y))


@case("opv2v", "yaml_binary", "wrong dtype")
def _(d):
    y = opv2v_scenario(d, "")
    y.write_bytes(b"\xff\xfe\x00lidar_pose\x80\x81")
    return Probe(says=(str(y), "yaml", "a readable UTF-8 yaml file"), call=_read_opv2v(y))


@case("opv2v", "lidar_pose_missing", "missing keys")
def _(d):
    doc = opv2v_doc()
    del doc["lidar_pose"]
    y = opv2v_scenario(d, doc)
    return Probe(says=(str(y), "lidar_pose", "a list of 6 numbers", "missing"), call=_read_opv2v(y))


@case("opv2v", "lidar_pose_5_numbers", "misaligned")
def _(d):
    y = opv2v_scenario(d, opv2v_doc(lidar_pose=[10.0, 5.0, 1.9, 0.0, 30.0]))
    return Probe(says=(str(y), "lidar_pose", "a list of 6 numbers"), call=_read_opv2v(y))


@case("opv2v", "lidar_pose_nan", "nan/inf")
def _(d):
    y = opv2v_scenario(d, yaml.safe_dump(opv2v_doc()).replace("- 30.0", "- .nan", 1))
    return Probe(says=(str(y), "lidar_pose", "finite numbers"), call=_read_opv2v(y))


@case("opv2v", "vehicle_location_strings", "wrong dtype")
def _(d):
    doc = opv2v_doc()
    doc["vehicles"][7]["location"] = ["20", "5", "0.5"]
    y = opv2v_scenario(d, doc)
    return Probe(says=(str(y), "vehicles.7.location", "3 numbers"), call=_read_opv2v(y))


@case("opv2v", "vehicle_extent_missing", "missing keys")
def _(d):
    doc = opv2v_doc()
    del doc["vehicles"][7]["extent"]
    y = opv2v_scenario(d, doc)
    return Probe(says=(str(y), "vehicles.7.extent", "a list of 3 numbers", "missing"), call=_read_opv2v(y))


@case("opv2v", "vehicle_extent_zero", "wrong units")
def _(d):
    doc = opv2v_doc()
    doc["vehicles"][7]["extent"] = [2.0, 0.0, 0.75]
    y = opv2v_scenario(d, doc)
    return Probe(says=(str(y), "vehicles.7.extent", "positive half sizes"), call=_read_opv2v(y))


@case("opv2v", "vehicle_id_not_integer", "wrong dtype")
def _(d):
    doc = opv2v_doc()
    doc["vehicles"] = {"car-7": doc["vehicles"][7]}
    y = opv2v_scenario(d, doc)
    return Probe(says=(str(y), "vehicles.car-7", "an integer vehicle id"), call=_read_opv2v(y))


@case("opv2v", "pcd_missing_beside_yaml", "missing keys")
def _(d):
    y = opv2v_scenario(d)
    y.with_suffix(".pcd").unlink()
    return Probe(says=(str(y.with_suffix(".pcd")), "pcd", "a point cloud beside"), call=_read_opv2v(y))


@case("opv2v", "pcd_truncated", "truncated")
def _(d):
    y = opv2v_scenario(d)
    pcd = y.with_suffix(".pcd")
    pcd.write_bytes(pcd.read_bytes()[:-7])
    return Probe(says=(str(pcd), "DATA", "truncated"), call=_read_opv2v(y))


@case("opv2v", "scenario_without_agents", "empty")
def _(d):
    s = d / "scn"
    s.mkdir()
    return Probe(says=(str(s), "agents", "at least one agent folder"), call=lambda: list_agents(s))


@case("opv2v", "root_is_a_file", "unreadable")
def _(d):
    r = write(d / "train", "not a folder")
    return Probe(says=(str(r), "root", "a folder of OPV2V-layout scenarios"), call=lambda: list_scenarios(r))


@case("opv2v", "yaml_no_permission", "unreadable", needs_non_root=True)
def _(d):
    y = unreadable(opv2v_scenario(d))
    return Probe(says=(str(y), "yaml", "a readable UTF-8 yaml file", "PermissionError"), call=_read_opv2v(y))
