"""Plane graph, trihedral angles, plane-based objects, classes and sizes (paper 4.2-4.3)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ObjectConfig:
    """Parameters of the plane graph, corners, objects and classification."""

    gravity_up_cam: tuple[float, ...] = ()
    """Up direction (opposite to gravity) in the camera frame when known; empty: estimate it."""
