"""Global relocalization in a point-cloud map (seed 000 §IV-C1): simulated LiDAR scans
(:mod:`.scan`), rotation-aware place descriptors (:mod:`.descriptor`), the place database of a map
(:mod:`.database`) and one-scan relocalization with coarse-to-fine ICP (:mod:`.relocalize`).
See docs/relocalization.md."""
