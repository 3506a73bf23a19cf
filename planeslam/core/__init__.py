"""Core: geometry, camera model, errors, config machinery, plane fitting maths and the
native-library settings. Imports nothing else of planeslam."""
