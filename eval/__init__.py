"""Trajectory evaluation, reports and the benchmark harness (installed as `planeslam.eval`)."""
