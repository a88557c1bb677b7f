"""Background jobs: the runner interface, the embedded process runner, the tasks."""
