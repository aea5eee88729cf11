"""Vehicle providers: the embedded simulator (:mod:`btmission.backends.sim`), kinematic test
vehicles (:mod:`btmission.backends.fake`) and PX4/ArduPilot over MAVLink
(:mod:`btmission.backends.mavlink`). Each implements the vehicle interface of
:mod:`btmission.vehicles`."""
