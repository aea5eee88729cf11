"""World maps: voxel maps (:mod:`.voxel`), map files (:mod:`.io`), the seeded mine generator and
its LiDAR survey (:mod:`.minegen`), a mission's world (:mod:`.build`), mission checks against the
map (:mod:`.checks`) and top-view pictures (:mod:`.render`). See docs/planner.md."""
