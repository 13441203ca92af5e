"""Stage summaries as Prefect markdown artifacts, and typ's loggers in Prefect's logging.

Without a server: the helper is a no-op outside a run, and the CLI's environment puts Prefect's
API handler on the ``typ`` and ``tasks`` loggers. With Prefect's temporary local server (in a
subprocess with its own PREFECT_HOME, set up as the CLI sets it up): a flow's ``typ`` log line and
its summary come back through the API, as the UI shows them, and that API refuses a request
without the project's secret.
"""
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from flows.common import artifact_key, publish_markdown
from typ.errors import TypError
from repo_paths import REPO

ROOT = REPO


def _env(tmp_path, **extra):
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env.update(PREFECT_HOME=str(tmp_path / ".prefect"), PYTHONPATH=str(ROOT), **extra)
    return env


def _python(script: str, tmp_path, env, timeout: float) -> str:
    result = subprocess.run([sys.executable, "-c", textwrap.dedent(script)], cwd=tmp_path, env=env,
                            capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, result.stderr[-3000:]
    return result.stdout


def test_outside_a_run_there_is_nothing_to_publish_to():
    assert publish_markdown("# summary", key="evaluate") is None
    assert artifact_key("Evaluate summary/Tiny_1") == "evaluate-summary-tiny-1"
    with pytest.raises(TypError, match="key"):
        artifact_key("__")


def test_the_cli_environment_puts_prefects_api_handler_on_typs_loggers(tmp_path):
    out = _python("""
        import os, warnings
        from pathlib import Path
        from flows.run import setup_env
        os.environ["PREFECT_LOGGING_EXTRA_LOGGERS"] = "mine"
        setup_env(Path("."))
        print(os.environ["PREFECT_LOGGING_EXTRA_LOGGERS"])
        import logging
        import flows.generic  # a flow module imports prefect, which sets up its logging
        from prefect.logging.handlers import APILogHandler
        for name in ("typ", "tasks", "mine"):
            print(name, any(isinstance(h, APILogHandler) for h in logging.getLogger(name).handlers))
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            logging.getLogger("typ.x").warning("outside any flow run: stays local, no Prefect warning")
        print("quiet")
    """, tmp_path, _env(tmp_path), timeout=120)
    assert out.split("\n")[:5] == ["mine,typ,tasks", "typ True", "tasks True", "mine True", "quiet"]


def test_a_flows_summary_and_typ_log_reach_the_prefect_api(tmp_path):
    env = _env(tmp_path, PREFECT_LOGGING_EXTRA_LOGGERS="typ,tasks", PREFECT_LOGGING_TO_API_WHEN_MISSING_FLOW="ignore",
               PREFECT_SERVER_ANALYTICS_ENABLED="false", DO_NOT_TRACK="1", PREFECT_LOGGING_LEVEL="WARNING",
               PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS="180")
    env["PYTHONPATH"] += os.pathsep + str(ROOT / "tests" / "helpers")   # the tests' api_status
    out = _python("""
        import logging
        from pathlib import Path
        from flows.run import setup_env
        from prefect_api import api_status
        setup_env(Path("."))  # before Prefect is imported, as the CLI does

        from prefect import flow
        from prefect.context import FlowRunContext
        from prefect.logging.handlers import APILogHandler
        from flows.common import publish_markdown

        @flow(name="summary-probe")
        def probe():
            logging.getLogger("typ.evaluate").warning("scored 8 samples")
            art = publish_markdown("# Evaluate\\n\\n| method | IoU |\\n|---|---|\\n| TYP | 0.412 |", key="evaluate_summary",
                                   description="tiny")
            return str(FlowRunContext.get().flow_run.id), art

        run_id, art = probe()
        APILogHandler().flush()
        from prefect.client.orchestration import get_client
        from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterKey, LogFilter, LogFilterFlowRunId
        with get_client(sync_client=True) as client:
            for auth in (None, Path(".prefect/api-auth").read_text().strip()):
                print(api_status(str(client.api_url).rstrip("/"), auth))
            logs = client.read_logs(log_filter=LogFilter(flow_run_id=LogFilterFlowRunId(any_=[run_id])))
            print([(l.name, l.message) for l in logs if l.name.startswith("typ")])
            arts = client.read_artifacts(artifact_filter=ArtifactFilter(key=ArtifactFilterKey(any_=["evaluate-summary"])))
            print([(str(a.id) == art, a.type, str(a.flow_run_id) == run_id, a.description, a.data) for a in arts])
    """, tmp_path, env, timeout=300)
    lines = out.strip().split("\n")
    assert lines[-4:-2] == ["401", "200"]   # without the secret, with it
    assert lines[-2] == "[('typ.evaluate', 'scored 8 samples')]"
    assert lines[-1] == ("[(True, 'markdown', True, 'tiny', '# Evaluate\\n\\n| method | IoU |\\n|---|---|\\n"
                         "| TYP | 0.412 |')]")
