"""Prefect flows: orchestration only — read params, call tasks, log to MLflow."""
