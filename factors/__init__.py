"""GTSAM factors for plane and trihedral-corner landmarks (installed as `planeslam.factors`)."""
