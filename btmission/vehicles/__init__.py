"""The vehicle interface: what the run loop knows of a vehicle, and nothing more.

* :mod:`btmission.vehicles.base`: one vehicle — :class:`~btmission.vehicles.base.Backend`
  (PX4-offboard-like commands, setpoints, telemetry) and its
  :class:`~btmission.vehicles.base.Sensors`;
* :mod:`btmission.vehicles.provider`: where vehicles come from — the
  :class:`~btmission.vehicles.provider.VehicleProvider` protocol and the ``btmission.providers``
  registry;
* :mod:`btmission.vehicles.clock`: the run's clock, which the provider owns.

The providers (:mod:`btmission.backends`: sim, fake, mavlink) implement it; the runtime uses it and
never names a provider (the layers are in pyproject.toml, checked by ``make lint``).
"""
