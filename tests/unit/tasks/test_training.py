"""Training loop: resume after a crash equals an uninterrupted run; divergence stops loudly."""
import pytest
import torch

from tasks.training import TrainingDiverged, batch_rng, checkpoints, run_loop


def _setup():
    torch.manual_seed(0)
    model = torch.nn.Linear(3, 1)
    opt = torch.optim.Adam(model.parameters(), lr=0.1)
    data = torch.randn(32, 3)
    target = data @ torch.tensor([[1.0], [-2.0], [0.5]])

    def step_fn(step, crash_at=None):
        if step == crash_at:
            raise KeyboardInterrupt("killed")
        idx = torch.from_numpy(batch_rng(0, step).choice(32, 8))
        loss = ((model(data[idx]) - target[idx]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        return {"loss": float(loss.detach())}

    return model, step_fn, {"model": model, "opt": opt}


def test_resume_matches_uninterrupted(tmp_path):
    model_a, step_a, state_a = _setup()
    full = run_loop(name="a", total_steps=10, step_fn=step_a, state=state_a,
                    checkpoint_dir=tmp_path / "a", checkpoint_every=3, curve=tmp_path / "a.csv")

    model_b, step_b, state_b = _setup()
    with pytest.raises(KeyboardInterrupt):
        run_loop(name="b", total_steps=10, step_fn=lambda s: step_b(s, crash_at=7), state=state_b,
                 checkpoint_dir=tmp_path / "b", checkpoint_every=3)
    assert [s for s, _ in checkpoints(tmp_path / "b")] == [3, 6]
    # a fresh process: new objects, state only from disk
    model_c, step_c, state_c = _setup()
    result = run_loop(name="c", total_steps=10, step_fn=step_c, state=state_c,
                      checkpoint_dir=tmp_path / "b", checkpoint_every=3, curve=tmp_path / "c.csv")
    assert result.resumed_from == 6 and result.steps_run == 4
    for pa, pc in zip(model_a.parameters(), model_c.parameters()):
        assert torch.equal(pa, pc)
    # the loss curve survives the crash: steps 0-5 come back from the checkpoint, 6-9 are new
    assert [h["step"] for h in result.history] == list(range(10)) and result.history == full.history
    assert (tmp_path / "c.csv").read_bytes() == (tmp_path / "a.csv").read_bytes()
    lines = (tmp_path / "a.csv").read_text().splitlines()
    assert lines[0] == "step,loss" and len(lines) == 11
    assert [float(line.split(",")[1]) for line in lines[1:]] == [h["loss"] for h in full.history]


def test_nan_loss_stops_and_keeps_last_good_checkpoint(tmp_path):
    model, step_fn, state = _setup()

    def poisoned(step):
        values = step_fn(step)
        return {"loss": float("nan")} if step == 4 else values

    with pytest.raises(TrainingDiverged, match=r"step 4: loss.*last good checkpoint: step_00000004.pt"):
        run_loop(name="t", total_steps=10, step_fn=poisoned, state=state,
                 checkpoint_dir=tmp_path, checkpoint_every=2)
    assert [s for s, _ in checkpoints(tmp_path)] == [2, 4]


def test_exploding_gradient_stops(tmp_path):
    model, step_fn, state = _setup()
    with pytest.raises(TrainingDiverged, match="grad_norm"):
        run_loop(name="t", total_steps=3, step_fn=lambda s: {**step_fn(s), "grad_norm": 1e9},
                 state=state, checkpoint_dir=tmp_path, checkpoint_every=1)


def test_a_finished_runs_checkpoints_go_and_nothing_else(tmp_path):
    """drop_checkpoints removes the run's folder of checkpoints and the empty folders above it up
    to the stage's output, and keeps a folder holding anything typ did not write there."""
    from tasks.training import drop_checkpoints, save_checkpoint

    out = tmp_path / "out"
    run = out / "checkpoints" / "oracle" / "single" / "seed_0" / "key1"
    save_checkpoint(run, 2, {"w": torch.zeros(1)})
    (out / "model.json").parent.mkdir(parents=True, exist_ok=True)
    (out / "model.json").write_text("{}")
    drop_checkpoints(run, up_to=out)
    assert sorted(p.name for p in out.iterdir()) == ["model.json"]
    mine = out / "checkpoints" / "generated" / "single" / "seed_0" / "key2"
    save_checkpoint(mine, 2, {"w": torch.zeros(1)})
    (mine / "notes.txt").write_text("a user's file")
    drop_checkpoints(mine, up_to=out)
    # typ's own checkpoint goes (its record proves it); the user's file, and so its folder, stay
    assert (mine / "notes.txt").read_text() == "a user's file" and sorted(p.name for p in mine.iterdir()) == ["notes.txt"]
