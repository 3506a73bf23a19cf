"""Files: dataset readers (TUM layout) and trajectory files (TUM format)."""
