"""Refresh dvc.lock's code-dependency entries (md5, size, nfiles) to the working tree.

    .venv/bin/python .ci/relock_code_deps.py

For a change that leaves every stage's outputs as they are (check that first: re-run the stages it
touches on a make-run workspace and compare the bytes): tests/e2e/test_dvc.py wants each code folder's
lock entry to cover the files git tracks there. Data dependencies, params and outs stay as locked;
a stage that gained a dependency other than code must be run instead (this script refuses)."""
from __future__ import annotations

import sys

import yaml
from dvc.dependency.param import ParamsDependency
from dvc.repo import Repo

CODE = ("typ", "tasks", "flows", "models", "pipelines", "cli")


def main() -> int:
    repo = Repo(".")
    with open("dvc.lock") as f:
        lock = yaml.safe_load(f)
    changed = 0
    for stage in repo.index.stages:
        entry = lock["stages"].get(stage.name)
        if entry is None:
            continue
        old = {d["path"]: d for d in entry.get("deps", [])}
        deps = []
        for dep in stage.deps:
            if isinstance(dep, ParamsDependency):
                continue
            path = str(dep.def_path)
            if path.split("/")[0] not in CODE:
                if path not in old:
                    print(f"{stage.name}: new dependency {path} is not code: run the stage", file=sys.stderr)
                    return 1
                deps.append(old[path])
                continue
            dep.save()
            saved = dep.dumpd()
            new = {"path": path, "hash": "md5", **{k: saved[k] for k in ("md5", "size", "nfiles") if k in saved}}
            changed += old.get(path) != new
            deps.append(new)
        entry["deps"] = sorted(deps, key=lambda d: d["path"])
    text = yaml.safe_dump(lock, sort_keys=False, width=10**6)
    text = text.replace(": null\n", ":\n")   # dvc writes an empty value bare
    with open("dvc.lock", "w") as f:
        f.write(text)
    print(f"{changed} code-dependency entries changed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
