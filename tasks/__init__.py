"""One module per stage: the stage's work as plain functions, wrapped thinly as Prefect tasks."""
