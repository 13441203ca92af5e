"""Process-tree measurement for bench/pipeline.py: a command and its descendants followed with psutil
(wall, peak RSS, the largest process's VmHWM, CPU seconds)."""
from __future__ import annotations

import subprocess
import threading
import time
from pathlib import Path

from bench.pipeline_report import POLL_S, STAGE_CMD


# ---------------------------------------------------------------- process-tree measurement


def _hwm_mb(pid: int) -> float:
    """The kernel's peak resident set size of ``pid`` (VmHWM), MB; 0 when unreadable."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except (OSError, ValueError):
        pass
    return 0.0


class StageMonitor(threading.Thread):
    """Follows the descendants of ``pid`` and charges each to the `typ run <stage>` process above it.

    Per stage: ``start``/``end`` (perf_counter s), ``peak_rss_mb`` (largest sampled tree sum),
    ``peak_process_mb`` (largest VmHWM seen), ``cpu_s`` (user + system, processes as last seen).
    """

    def __init__(self, pid: int, *, interval: float = POLL_S, label: str | None = None):
        super().__init__(daemon=True)
        import psutil

        self._psutil, self.root, self.interval = psutil, psutil.Process(pid), interval
        self.fixed_label = label  # charge the root and its whole tree to this label
        self._halt = threading.Event()
        self._stage_of: dict[tuple[int, float], str | None] = {}
        self._cpu: dict[tuple[int, float], tuple[str, float]] = {}
        self.stages: dict[str, dict] = {}

    def run(self) -> None:
        while not self._halt.is_set():
            self.poll()
            self._halt.wait(self.interval)

    def stop(self) -> dict[str, dict]:
        self._halt.set()
        self.join()
        for stage, cpu in self._cpu.values():
            self.stages[stage]["cpu_s"] += cpu
        return {s: {"seconds": v["end"] - v["start"], **{k: v[k] for k in ("peak_rss_mb", "peak_process_mb",
                                                                         "cpu_s")}}
                for s, v in self.stages.items()}

    def _label(self, proc, parent_label: str | None) -> str | None:
        key = (proc.pid, proc.create_time())
        if key not in self._stage_of:
            match = STAGE_CMD.search(" ".join(proc.cmdline()))
            self._stage_of[key] = match.group(1) if match else None
        return parent_label or self._stage_of[key]

    def poll(self) -> None:
        psutil = self._psutil
        now = time.perf_counter()
        try:
            procs = self.root.children(recursive=True)
        except psutil.Error:
            return
        if self.fixed_label is not None:
            procs.append(self.root)
        by_pid = {p.pid: p for p in procs}
        labels: dict[int, str | None] = {}

        def label(p) -> str | None:  # the outermost `typ run <stage>` at or above p
            if self.fixed_label is not None:
                return self.fixed_label
            if p.pid not in labels:
                labels[p.pid] = None  # cycle guard
                try:
                    parent = by_pid.get(p.ppid())
                    labels[p.pid] = self._label(p, label(parent) if parent is not None else None)
                except psutil.Error:
                    pass
            return labels[p.pid]

        rss: dict[str, float] = {}
        for p in procs:
            stage = label(p)
            if stage is None:
                continue
            try:
                with p.oneshot():
                    key = (p.pid, p.create_time())
                    mem, cpu = p.memory_info().rss / 2**20, p.cpu_times()
            except psutil.Error:
                continue
            # seen between two polls: charge half an interval on either side (create_time is
            # relative to a boot time the kernel gives in whole seconds: too coarse)
            entry = self.stages.setdefault(stage, {"start": now - self.interval / 2, "peak_rss_mb": 0.0,
                                                   "peak_process_mb": 0.0, "cpu_s": 0.0})
            entry["end"] = now + self.interval / 2
            entry["peak_process_mb"] = max(entry["peak_process_mb"], _hwm_mb(p.pid), mem)
            self._cpu[key] = (stage, cpu.user + cpu.system)
            rss[stage] = rss.get(stage, 0.0) + mem
        for stage, total in rss.items():
            self.stages[stage]["peak_rss_mb"] = max(self.stages[stage]["peak_rss_mb"], total)


def measured(cmd: list[str], cwd: Path, env: dict, *, label: str | None = None) -> dict:
    """Run ``cmd``; its wall time, stdout, and per-stage numbers of the `typ run` processes it starts
    (``label``: the whole process tree of ``cmd``, itself included, counts as that one stage)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    monitor = StageMonitor(proc.pid, label=label)
    monitor.start()
    stdout, stderr = proc.communicate()
    seconds = time.perf_counter() - t0
    stages = monitor.stop()
    if proc.returncode != 0:
        done = ", ".join(f"{k} {v['seconds']:.1f} s" for k, v in stages.items())
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}) in {cwd} after {seconds:.1f} s "
                           f"({done}):\n{stdout[-3000:]}\n{stderr[-5000:]}")
    return {"seconds": seconds, "stages": stages, "ran": list(stages), "noop": "Running stage" not in stdout}
