"""Vehicle backends: the :class:`~btmission.backends.base.Backend` interface (PX4-offboard-like)
and the embedded simulator (:mod:`btmission.backends.sim`)."""
