"""The per-frame front end (paper Sections 3-4.3): organised cloud, plane segmentation,
real intersections (eq. 1-6), plane graph, trihedral corners, objects with classes and sizes.
`pipeline.FrontEnd` runs the stages in order."""
