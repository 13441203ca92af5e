"""torch nn.Modules and losses only: no file I/O, no Prefect, no MLflow."""
