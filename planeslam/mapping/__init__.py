"""The world plane-object map: data model, the paper's merge (Section 4.4), objects
re-aggregated, the sparse non-planar cloud, map files."""
