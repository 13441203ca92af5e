"""The bad-input corpus (tests/fuzz/bad_inputs/make_corpus.py): every case fails with typ's own error.

Each case must raise :class:`typ.errors.TypError` (through the CLI: exit code 2, the message on
stderr) whose text names the file or field and what was expected, and must leave the files it
was given, and any earlier outputs, byte for byte as they were: no partial or temporary file.
A reader case runs in a child process bounded to 2 s and 1 GiB more memory (tests/helpers/bounded.py):
inputs built to hang, exhaust memory or crash the interpreter fail their case, not the suite.
The one case that runs a whole stage uses the session's Prefect server (tests/e2e/test_crash_safety.py).
"""
from __future__ import annotations

import os
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

from bad_inputs.make_corpus import CASES, KINDS, Case
from bounded import run_bounded
from stage_processes import stage_env

READERS = {"binfile", "pcd", "opv2v", "kitti", "nuscenes", "waymo", "store", "voxel", "params", "cli", "artifact",
           "show", "io", "kitti-odometry"}
#: what one bad input may take: a named error within this time and this much more memory
SECONDS, MEMORY = 2.0, 1 << 30


@pytest.fixture(scope="module", autouse=True)
def _compiled_kernels():
    """Compile (or load from numba's cache) the numba kernels once here, the LZF decoder and the
    voxel scatter: the bounded children inherit them, and the 2 s of a case measure its input,
    not a one-off compilation (several seconds on a busy machine)."""
    import numpy as np

    from typ.formats.pcd import lzf_decompress
    from typ.voxel import TINY_GRID, voxelize

    lzf_decompress(bytes([0, 7]), 1)
    for dtype in (np.float32, np.float64):  # one compiled signature per dtype of points
        voxelize(np.zeros((1, 4), dtype), TINY_GRID)


def snapshot(folder: Path) -> dict[str, object]:
    """Every path under ``folder`` with its bytes (None for folders, FIFOs and files we may not read;
    size and modification time for the sparse files of gigabytes, which typ must not even read)."""
    if not folder.exists():
        return {}

    def state(p: Path):
        if not p.is_file() or not os.access(p, os.R_OK):
            return None
        info = p.stat()
        return (info.st_size, info.st_mtime_ns) if info.st_size > 1 << 26 else p.read_bytes()

    # a .typ/ folder is typ's own state (gitignored, dvcignored), wherever it is: the lock beside an output
    # folder (typ.io.output_lock) stays by design, as removing a lock file another run waits on would let a
    # third one in; never a user's output
    return {str(p.relative_to(folder)): state(p) for p in sorted(folder.rglob("*"))
            if ".typ" not in p.relative_to(folder).parts}


def run_stage_process(argv: list[str], cwd: Path, env: dict) -> tuple[int, str]:
    """``python -m cli ARGV``; Prefect's and MLflow's state live outside the project (``env``)."""
    proc = subprocess.run([sys.executable, "-m", "cli", *argv], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=600)
    return proc.returncode, proc.stderr


def test_the_corpus_covers_every_reader_and_kind():
    assert len(CASES) >= 45
    assert len({c.id for c in CASES}) == len(CASES)
    assert {c.reader for c in CASES} == READERS
    kinds = Counter(c.kind for c in CASES)
    assert set(kinds) == set(KINDS), set(KINDS) - set(kinds)


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_is_named_and_touches_nothing(case: Case, tmp_path, capsys, request, tmp_path_factory):
    if case.needs_non_root and os.geteuid() == 0:
        pytest.skip("root reads files whatever their permissions")
    if case.needs:
        pytest.importorskip(case.needs)
    probe = case.build(tmp_path)
    watch = probe.watch or tmp_path
    before = snapshot(watch)
    assert before or probe.call is not None, "a CLI case must have earlier outputs to protect"

    if probe.call is not None:
        outcome = run_bounded(probe.call, seconds=SECONDS, memory=MEMORY, keep=lambda value: value)
        if probe.returns is not None:
            assert outcome.kind == "returned" and outcome.value == probe.returns, str(outcome)
            return
        assert outcome.kind == "TypError", str(outcome)
        message = outcome.text
        assert ": expected " in message
    elif probe.argv is not None:
        from cli.main import main

        try:
            code = main(probe.argv)
        except SystemExit as exc:  # argparse: usage errors exit 2 by themselves
            code = exc.code
        message = capsys.readouterr().err
        assert code == 2, message
        assert message.strip() and "Traceback" not in message
    else:
        code, message = run_stage_process(probe.process, probe.cwd, stage_env(request.config, tmp_path_factory))
        assert code == 2, message[-3000:]
        assert "Traceback" not in message, message[-3000:]   # bad input: no stack, Prefect's log included
        message = message.strip().splitlines()[-1]  # the CLI's own last word, after Prefect's log
        assert message.startswith("typ: error: "), message

    for text in probe.says:
        assert text in message, f"{text!r} not in: {message}"
    assert snapshot(watch) == before  # earlier outputs untouched, nothing partial or temporary left
