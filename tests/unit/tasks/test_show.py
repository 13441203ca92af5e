"""`typ show` on a simulated scenario and on a generated copy of it: every PNG, the true view found
in the simulated file or cast again from the simulator, and the scores against it."""
import dataclasses
import json

import matplotlib.image as mpimg
import numpy as np
import pytest

from tasks.show import ShowOptions, find_truth, reference_vehicle, scenario_folders, show
from tasks.sim_truth import scenario_job, true_view
from tasks.simulate import ScenarioJob, run_job
from typ import viz
from cli.main import main
from typ.errors import TypError
from typ.formats.opv2v import read_scene, write_scene
from typ.geometry import pose_to_matrix
from typ.io import write_json
from typ.metrics.truth import occupancy_iou
from typ.scene import AgentView
from typ.voxel import TINY_GRID, voxelize

JOB = ScenarioJob("target", "test", 0, seed=7, n_agents=2, n_frames=2, azimuth_step_deg=1.0, comm_range=70.0, dt=0.1)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """data/sim/target/test/target_test_0000 (simulated) and data/generated/... with two generated agents:
    one on a labelled vehicle (``<ego><vehicle>``, truth cast again) and one named like the second CAV
    with its true pose (a ``cavs``-style agent whose truth is the simulated file)."""
    root = tmp_path_factory.mktemp("data")
    run_job(JOB, root / "sim")
    sim = JOB.folder(root / "sim")
    scene = read_scene(sim, "000001")
    ego_id, cav_id = list(scene.agents)
    ego = scene.agents[ego_id]
    far = np.argmax(np.hypot(ego.boxes[:, 0], ego.boxes[:, 1]) < 30.0)  # a labelled vehicle within 30 m
    vid = int(ego.box_ids[far])
    box = ego.boxes[far]
    pose = ego.pose @ pose_to_matrix([box[0], box[1], 0.0, 0.0, np.degrees(box[6]), 0.0])
    truth, _ = true_view(scenario_job(sim), "000001", pose, vehicle_id=vid)
    gen = root / "generated" / "target" / "test" / sim.name
    views = {ego_id: ego,
             f"{ego_id}{vid}": AgentView(f"{ego_id}{vid}", truth, pose, ego.boxes[:2], ego.box_labels[:2], ego.box_ids[:2]),
             cav_id: dataclasses.replace(scene.agents[cav_id], semantics=None)}
    gen.mkdir(parents=True)
    for ts in ("000000", "000001"):
        write_scene(dataclasses.replace(scene, scenario=gen.name, timestamp=ts, agents=views), gen)
    write_json(gen / "_typ.json", {"generated_agents": sorted([f"{ego_id}{vid}", cav_id]), "references": "vehicles"})
    return root, sim, gen, ego_id, cav_id, vid, pose


def test_the_simulator_cast_again_sees_what_the_stored_view_saw(data):
    root, sim, *_ = data
    job = scenario_job(sim)
    assert job == JOB
    scene = read_scene(sim, "000000")
    for agent_id, view in scene.agents.items():
        points, semantics = true_view(job, "000000", view.pose, vehicle_id=int(agent_id))
        again, _ = true_view(job, "000000", view.pose, vehicle_id=int(agent_id))
        assert np.array_equal(points, again) and len(semantics) == len(points)
        # the same world: only dropout and range noise are drawn afresh
        iou = occupancy_iou(voxelize(points, TINY_GRID), voxelize(view.points, TINY_GRID))["iou"]
        assert iou > 0.85, (agent_id, iou)
    with pytest.raises(TypError, match="timestamp"):
        true_view(job, "000002", scene.ego.pose)
    with pytest.raises(TypError, match="vehicle_id"):
        true_view(job, "000000", scene.ego.pose, vehicle_id=10**6)


def test_a_changed_simulator_key_means_no_truth_to_cast(data, tmp_path):
    import shutil

    _, sim, *_ = data
    copy = tmp_path / sim.name
    shutil.copytree(sim, copy)
    manifest = json.loads((copy / "_typ.json").read_text())
    manifest["key"] = "0" * 64
    (copy / "_typ.json").write_text(json.dumps(manifest))
    assert scenario_job(copy) is None
    assert find_truth("000000", np.eye(4), None, copy, None) == (None, "none")


def test_generated_agents_name_their_vehicle(data):
    _, sim, _, _, _, vid, _ = data
    ego = read_scene(sim, "000000").ego
    assert reference_vehicle(f"{ego.agent_id}{vid}", ego, "vehicles") == vid
    assert reference_vehicle(f"{ego.agent_id}999999", ego, "vehicles") is None  # not a labelled vehicle
    assert reference_vehicle("-1", ego, "vehicles") is None
    assert reference_vehicle("42", ego, "cavs") == 42


def test_show_writes_every_png_and_scores_generated_views_against_their_truth(data, tmp_path):
    root, sim, gen, ego_id, cav_id, vid, _ = data
    opts = ShowOptions(grid=TINY_GRID, window=viz.Window(resolution=0.4))
    written = show(gen, tmp_path, opts, "000001")
    names = sorted(p.name for p in written)
    prefix = f"{gen.name}_000001"
    agents = sorted([ego_id, cav_id, f"{ego_id}{vid}"])
    expected = {f"{prefix}_agents.png", *(f"{prefix}_{a}.png" for a in agents),
                *(f"{prefix}_{a}_range.png" for a in agents),
                f"{prefix}_{ego_id}{vid}_sample.png", f"{prefix}_{cav_id}_sample.png"}
    assert set(names) == expected and len(names) == len(expected)
    for path in written:
        img = mpimg.imread(path)
        assert img[..., :3].std() > 0.05, path.name
    # the generated views are their truths: cast again (on a vehicle) and the simulated file (a CAV)
    scene = read_scene(gen, "000001")
    from tasks.show import generated_sample, simulated_counterpart

    for agent, how in ((f"{ego_id}{vid}", "re-cast"), (cav_id, "simulated file")):
        sample = generated_sample(scene, agent, references="vehicles" if agent != cav_id else "cavs",
                                  sim_folder=simulated_counterpart(gen, opts), job=scenario_job(sim), spec=None,
                                  opts=opts)
        assert sample["titles"]["true"] == f"true view ({how})"
        assert sample["scores"]["iou"] == 1.0 and sample["scores"]["chamfer_m"] == 0.0
    # a scenario with no simulated counterpart has no truth, and says so by leaving the panel out
    elsewhere = ShowOptions(grid=TINY_GRID, window=viz.Window(resolution=0.4), sim_root=tmp_path / "nowhere",
                            resim=False)
    sample = generated_sample(scene, cav_id, references="cavs", sim_folder=simulated_counterpart(gen, elsewhere),
                              job=None, spec=None, opts=elsewhere)
    assert "true" not in sample and "iou" not in sample["scores"]


def test_typ_show_cli_on_a_split_and_on_bad_input(data, tmp_path, capsys):
    root, sim, gen, ego_id, *_ = data
    assert scenario_folders(sim.parent) == [sim]
    assert main(["--root", str(tmp_path), "show", str(sim.parent), "--out", str(tmp_path / "out"), "--no-resim",
                 "--range", "30", "--color", "class"]) == 0
    out = capsys.readouterr().out
    assert f"{sim.name}_000000_agents.png" in out and f"{sim.name}_000000_{ego_id}_range.png" in out
    assert main(["show", str(sim), "--timestamp", "000009", "--out", str(tmp_path)]) == 2
    assert "--timestamp: expected one of ['000000', '000001']" in capsys.readouterr().err
    assert main(["show", str(tmp_path / "missing"), "--out", str(tmp_path)]) == 2
    assert main(["show", str(sim), "--sensor", "lidar9", "--out", str(tmp_path)]) == 2
