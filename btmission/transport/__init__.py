"""The network transport between the coordinator and the agents (DESIGN.md §3): Eclipse Zenoh.

* :mod:`btmission.transport.keys` — the key expressions (pure; no Zenoh needed);
* :mod:`btmission.transport.zenoh_link` — :class:`~btmission.transport.zenoh_link.
  ZenohCoordinatorLink` and :class:`~btmission.transport.zenoh_link.ZenohAgentLink`, the
  :class:`~btmission.links.bus.CoordinatorLink` and :class:`~btmission.links.bus.AgentLink`
  over a Zenoh session, carrying exactly the :mod:`btmission.links.wire` encodings;
* :mod:`btmission.transport.zenoh_session` — :class:`~btmission.transport.zenoh_session.
  ZenohSettings` and opening a session, the transport's errors, the endpoint helpers;
* :mod:`btmission.transport.zenoh_plumbing` — what the links share underneath: the checks of
  what arrives, the counters, the decode cache, the mailbox, the publishers;
* :mod:`btmission.transport.faulty` — a test wrapper that duplicates, delays and reorders
  messages (seeded), around the in-memory bus or Zenoh links alike.

Zenoh is the optional ``net`` extra (``pip install 'btmission[net]'``): neither ``import
btmission`` nor this package imports it; :mod:`~btmission.transport.zenoh_session` does when a
session is opened, and says how to install it when it is missing. See docs/distributed.md.
"""
