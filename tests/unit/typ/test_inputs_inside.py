"""Every path a dataset names stays inside its root (:func:`typ.inputs.inside`), and nothing outside is read.

- ``inside`` itself: relative, absolute, ``..`` and links, each case that leaves the root refused
  with a TypError naming the index and its field, the root itself a link allowed.
- The corpus's path cases (tests/fuzz/bad_inputs/cases_paths.py: nuScenes, KITTI, Waymo, OPV2V; absolute,
  ``..``, a link out): each is refused, and an audit hook sees no file under the case's ``outside``
  folder opened, which is where each escape leads (a valid file: had it been read, the call would
  have returned).
- What stays legitimate: a root reached through a link, scenarios whose files are hard links (as
  ``simulate.sources`` takes an OPV2V dataset), links that stay inside the root, and OPV2V scenario
  and agent folders that are links (copies assembled from a dataset kept elsewhere: each folder is
  read as the folder it leads to, whose files must lie in it, typ.formats.opv2v.agent_file).
- ``typ edit --compose cast`` on a scenario whose yaml names ``sensor: ../../etc/passwd`` names that
  yaml and its ``sensor`` field, not params.yaml.
"""
from __future__ import annotations

import os
import sys
import types

import pytest
import yaml

from bad_inputs.make_corpus import CASES, opv2v_doc, opv2v_scenario
from typ.errors import TypError
from typ.inputs import inside

PATH_CASES = [c for c in CASES if c.build.__module__ == "bad_inputs.cases_paths"]

#: paths opened while a test records them (an audit hook cannot be removed: it stays, idle, after)
_OPENED: list[str] | None = None


def _record_opens(event: str, args: tuple) -> None:
    if _OPENED is not None and event == "open" and isinstance(args[0], (str, bytes, os.PathLike)):
        _OPENED.append(os.path.realpath(os.fsdecode(args[0])))


sys.addaudithook(_record_opens)


def opened_while(call) -> tuple[list[str], BaseException | None, object]:
    """(the real paths of the files ``call()`` opened, what it raised, what it returned)."""
    global _OPENED
    _OPENED = []
    try:
        value, raised = call(), None
    except BaseException as exc:  # noqa: BLE001 (the caller asserts on it)
        value, raised = None, exc
    finally:
        opened, _OPENED = _OPENED, None
    return opened, raised, value


# ---------------------------------------------------------------- inside()


def test_inside_accepts_what_stays_in_the_root_and_returns_the_path_named(tmp_path):
    root = tmp_path / "data"
    (root / "a").mkdir(parents=True)
    (root / "a" / "x.bin").write_bytes(b"x")
    (root / "alias.bin").symlink_to("a/x.bin")            # a link that stays inside
    assert inside("a/x.bin", root) == root / "a" / "x.bin"
    assert inside("a/../a/x.bin", root) == root / "a/../a/x.bin"   # a '..' that stays inside
    assert inside(root / "a" / "x.bin", root) == root / "a" / "x.bin"   # absolute, inside
    assert inside("alias.bin", root) == root / "alias.bin"          # the name, not the link's target
    assert inside("not/there.bin", root) == root / "not" / "there.bin"   # missing: the reader says so


@pytest.mark.parametrize("escape", ["absolute", "climbs", "link", "dangling link", "link in the way"])
def test_inside_refuses_each_way_out_naming_the_index_and_field(tmp_path, escape):
    root, outside = tmp_path / "data", tmp_path / "outside"
    (root / "a").mkdir(parents=True)
    outside.mkdir()
    (outside / "x.bin").write_bytes(b"secret")
    path = {"absolute": str(outside / "x.bin"), "climbs": "a/../../outside/x.bin", "link": "a/x.bin",
            "dangling link": "a/x.bin", "link in the way": "b/x.bin"}[escape]
    if escape == "link":
        (root / "a" / "x.bin").symlink_to(outside / "x.bin")
    elif escape == "dangling link":
        (root / "a" / "x.bin").symlink_to(outside / "not-yet.bin")
    elif escape == "link in the way":
        (root / "b").symlink_to(outside)
    with pytest.raises(TypError) as raised:
        inside(path, root, where=root / "index.json", field="data_list[3].lidar_path")
    err = raised.value
    assert (err.where, err.field) == (str(root / "index.json"), "data_list[3].lidar_path")
    assert f"a path inside {root}" in str(err) and path in str(err) and str(outside) in str(err)


def test_inside_takes_a_root_that_is_a_link_by_its_real_path(tmp_path):
    real = tmp_path / "store" / "kitti"
    (real / "training").mkdir(parents=True)
    (tmp_path / "data").mkdir()
    root = tmp_path / "data" / "kitti"
    root.symlink_to(real)                                  # the user's link to a dataset kept elsewhere
    assert inside("training", root) == root / "training"
    assert inside(real / "training", root) == real / "training"
    (real / "up").symlink_to(tmp_path / "data")            # a link in it that leads back out is not
    with pytest.raises(TypError, match="real path"):
        inside("up", root)


# ---------------------------------------------------------------- the corpus's escapes: refused, nothing read


@pytest.mark.parametrize("case", PATH_CASES, ids=[c.id for c in PATH_CASES])
def test_no_escape_opens_a_file_outside_the_root(case, tmp_path):
    probe = case.build(tmp_path)
    opened, raised, value = opened_while(probe.call)
    if probe.returns is not None:   # legitimate: the root itself is a link to the dataset
        assert raised is None and value == probe.returns
        return
    assert isinstance(raised, TypError), raised
    outside = os.path.realpath(tmp_path / "outside")
    assert not [p for p in opened if p == outside or p.startswith(outside + os.sep)], opened


def test_the_corpus_has_each_escape_for_each_format():
    names = {c.id for c in PATH_CASES}
    for fmt in ("nuscenes", "kitti", "waymo", "opv2v"):
        assert any(n.startswith(f"{fmt}/") and "links_out" in n for n in names), fmt
    for fmt in ("nuscenes", "kitti", "opv2v"):
        assert any(n.startswith(f"{fmt}/") and ("climbs_out" in n) for n in names), fmt
    assert {"nuscenes/lidar_path_absolute", "opv2v/agent_absolute"} <= names


# ---------------------------------------------------------------- what stays legitimate


def test_a_scenario_of_hard_links_and_a_scenario_reached_through_a_link_read(tmp_path):
    """simulate.sources takes an OPV2V scenario into its output as hard links; a user may name a
    scenario through a link. Both are read as the files they are."""
    from typ.formats.opv2v import check_scenario, list_scenarios, read_scene

    y = opv2v_scenario(tmp_path / "dataset")
    copy = tmp_path / "out" / "train" / "scn" / "1"
    copy.mkdir(parents=True)
    for f in y.parent.iterdir():
        os.link(f, copy / f.name)
    assert list_scenarios(copy.parent.parent) == [copy.parent]
    assert check_scenario(copy.parent)["views"] == 1
    (tmp_path / "mine").symlink_to(y.parent.parent)
    assert read_scene(tmp_path / "mine", y.stem).ego.boxes.shape == (1, 7)
    (copy.parent.parent / "linked").symlink_to(y.parent.parent)   # a split of links to scenarios kept elsewhere
    assert list_scenarios(copy.parent.parent) == [copy.parent.parent / "linked", copy.parent]
    assert check_scenario(copy.parent.parent / "linked")["views"] == 1


# ---------------------------------------------------------------- typ edit: the yaml's sensor is named


def test_edit_cast_names_the_yaml_and_its_sensor_field_not_params(tmp_path, monkeypatch):
    import flows.generate
    from flows.edit import edit_scenario
    from tasks.edit import BoxEdit
    from tasks.generate import Generator
    from typ.voxel import TINY_GRID

    y = opv2v_scenario(tmp_path / "data", yaml.safe_dump({**opv2v_doc(), "sensor": "../../etc/passwd"}))
    (tmp_path / "params.yaml").write_text(yaml.safe_dump({"profile": "tiny"}))
    # the trained generator is not needed to look the sensor up: its grid and sensor lookup are the real ones
    generator = Generator(pipe=types.SimpleNamespace(grid=TINY_GRID), mount_height={}, digest="stub")
    monkeypatch.setattr(flows.generate, "load_generator", lambda root, cfg: generator)
    with pytest.raises(TypError) as raised:
        edit_scenario(y.parent.parent, y.stem, BoxEdit(), tmp_path / "out", root=tmp_path, params="params.yaml",
                      compose="cast")
    assert (raised.value.where, raised.value.field) == (str(y), "sensor")
    assert "params.yaml" not in str(raised.value) and not (tmp_path / "out").exists()
