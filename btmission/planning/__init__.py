"""The D*+ risk-aware planner: the eq. 3-4 cost layer (:mod:`.risk`), the searches — single
query, one-to-all, incremental replanning (:mod:`.dstar`, numba kernels in :mod:`._kernels`) —,
waypoint thinning (:mod:`.paths`) and the references the tests compare with (:mod:`.reference`).
See docs/planner.md."""
