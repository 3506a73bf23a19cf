"""The application layer: the CLI, the `run` command's runner, demo, benchmarks, the frame
command and overlays. Progress bars, logging set-up and process tuning live here only."""
