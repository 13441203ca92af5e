"""A real browser on the MLflow UI: `mlflow server` on loopback, headless Chromium loads a stage run's
page, and the logged render and score table are in the page it built.

Slow (about 35 s at one thread: the server's start and Chromium's first page), so it runs with
``TYP_SLOW=1 .venv/bin/python -m pytest -q tests/unit/flows/test_mlflow_ui.py``. It needs Debian's
``chromium`` (``make setup`` installs it when run as root), and is skipped without it.
"""
import os
import re
import shutil
import subprocess
import sys
import time
import urllib.request

import numpy as np
import pytest

from flows.server import free_port
from typ import viz
from typ.config import config_from_dict
from typ.tracking import stage_run

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not os.environ.get("TYP_SLOW"), reason="slow: runs with TYP_SLOW=1"),
    pytest.mark.skipif(CHROMIUM is None, reason="no chromium: install Debian's package (apt-get install chromium; "
                                                "make setup does it as root)"),
]
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--no-first-run"]


def _dom(url: str, profile) -> str:
    """The page's DOM after its scripts ran: virtual time lets the app fetch and render first."""
    result = subprocess.run([CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "--virtual-time-budget=20000",
                             "--dump-dom", url], capture_output=True, text=True, timeout=180)
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout


def test_the_run_page_shows_the_logged_render_and_score_table(tmp_path, monkeypatch):
    uri = f"sqlite:///{tmp_path / 'mlruns.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    cfg = config_from_dict({"profile": "tiny"})
    rng = np.random.default_rng(0)
    with stage_run("evaluate", cfg, root=tmp_path) as run:
        cloud = np.c_[rng.uniform(-40, 40, (500, 2)), rng.uniform(-2.5, 0.5, 500), np.zeros(500)].astype(np.float32)
        run.log_figure(viz.bev_figure(cloud, title="generated view"), "gallery/sample_0.png")
        run.log_table([{"sample": "town_a 000000 777748", "iou": 0.412}, {"sample": "town_b 000001 446565", "iou": 0.377}],
                      "scores.json")
    import mlflow

    experiment = mlflow.MlflowClient().get_run(run.run_id).info.experiment_id
    port = free_port()
    server = subprocess.Popen([os.path.join(os.path.dirname(sys.executable), "mlflow"), "server", "--backend-store-uri",
                               uri, "--host", "127.0.0.1", "--port", str(port), "--workers", "1"],
                              stdout=open(tmp_path / "server.log", "w"), stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 180
        while True:
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=2)
                break
            except OSError:
                assert server.poll() is None and time.monotonic() < deadline, (tmp_path / "server.log").read_text()
                time.sleep(0.5)
        page = f"http://127.0.0.1:{port}/#/experiments/{experiment}/runs/{run.run_id}/artifactPath"
        image = _dom(f"{page}/gallery/sample_0.png", tmp_path / "chrome")
        # the UI fetched the PNG through the server and shows it
        assert re.search(r'<img alt="gallery/sample_0.png" src="blob:http://127\.0\.0\.1:\d+/', image), image[-3000:]
        table = _dom(f"{page}/scores.json", tmp_path / "chrome")
        assert "showartifactloggedtableview" in table and 'role="table"' in table  # the logged-table viewer
        headers = re.findall(r'role="columnheader".*?title="([^"]+)"', table)
        assert headers == ["sample", "iou"]
        cells = re.findall(r'role="cell"[^>]*><span[^>]*>([^<]*)</span>', table)
        assert cells == ["town_a 000000 777748", "0.412", "town_b 000001 446565", "0.377"]
    finally:
        server.terminate()
        server.wait(timeout=30)
