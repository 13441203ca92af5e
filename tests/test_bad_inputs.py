"""The bad-input corpus (tests/bad_inputs/make_corpus.py): every case fails with typ's own error.

Each case must raise :class:`typ.errors.TypError` (through the CLI: exit code 2, the message on
stderr) whose text names the file or field and what was expected, and must leave the files it
was given, and any earlier outputs, byte for byte as they were: no partial or temporary file.
The one case that runs a whole stage uses the session's Prefect server (tests/test_crash_safety.py).
"""
from __future__ import annotations

import os
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

from bad_inputs.make_corpus import CASES, KINDS, Case
from test_crash_safety import stage_env
from typ.errors import TypError

READERS = {"binfile", "pcd", "opv2v", "kitti", "nuscenes", "waymo", "store", "voxel", "params", "cli", "artifact"}


def snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every path under ``folder`` with its bytes (None for folders and files we may not read)."""
    if not folder.exists():
        return {}
    return {str(p.relative_to(folder)): p.read_bytes() if p.is_file() and os.access(p, os.R_OK) else None
            for p in sorted(folder.rglob("*"))}


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
        with pytest.raises(TypError) as info:
            probe.call()
        message = str(info.value)
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
