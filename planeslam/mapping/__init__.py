"""The world plane-object map. `world_map.Map` is the public object; a module per job:

config           MapConfig (leaf)
records          MapError and the frozen plane, edge, corner and object records
gravity          the map's up vector: its typed source and how it follows the map
sparse_cloud     the voxel-averaged cloud for what is not planar
contents         the map's mutable state, which the modules below work on
seating          outlines and edge segments put on their planes
merge            the paper's frame-by-frame merge (Section 4.4)
reaggregation    the map graph and its objects (paper 4.2-4.3 on the merged map)
geometry_update  optimised landmarks from the backend written into the map
json_io          map files, schema 'planeslam.map/1'
ply_export       PLY files: the plane polygons (a coloured mesh), the sparse cloud (points)
memory           bytes per part
world_map        `Map`: read access, and each operation handed to its module
"""
