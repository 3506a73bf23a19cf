"""Backends behind the orchestrator: the iSAM2 factor graph (`isam2`), the child process
that runs it beside tracking (`worker`) and their config."""
