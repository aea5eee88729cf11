"""An agent's ``backend:``, read once: which vehicle provider, and an address only it reads.

``backend: sim`` names the embedded simulator; ``backend: mavlink+udp://127.0.0.1:14540`` the
``mavlink`` provider, its transport ``udp`` and the address ``127.0.0.1:14540``. The file model
checks the general form — a provider's scheme alone, or ``<scheme>[+<transport>]://<address>``
— and keeps the parts as a :class:`VehicleRef`; which schemes are installed, and what an address
means, is the provider's business (:func:`btmission.runtime.runcheck.backend_problems` asks it,
with the agent's line in the file, before anything runs).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

BACKEND_RE = r"^[a-z][a-z0-9+.-]*(:.*)?$"
"""What the file model accepts as a ``backend:``: a provider's scheme (lower-case letters,
digits, ``+ . -``), alone or followed by ``:`` and what its provider reads. The form a provider
without a check of its own expects is ``<scheme>://<address>`` (:attr:`VehicleRef.well_formed`);
the ``mavlink`` provider checks its URLs' grammar itself, to name what is wrong."""

EXPECTED = (
    "expected 'sim' or a vehicle provider's URL <scheme>://<address> such as "
    "mavlink+udp://127.0.0.1:14540 (scheme: lower-case letters, digits, + . -)"
)


@dataclass(frozen=True)
class VehicleRef:
    """Where an agent's vehicle comes from (module docstring)."""

    url: str
    """The ``backend:`` as written."""
    scheme: str
    """The provider: ``sim``, ``fake``, ``mavlink`` ... (``mavlink+udp`` → ``mavlink``)."""
    transport: str = ""
    """What follows ``+`` in the scheme (``udp``), for the provider to read; empty if none."""
    address: str = ""
    """What follows ``://`` (empty for a scheme alone), for the provider to read."""
    well_formed: bool = True
    """The scheme is alone or followed by ``://`` (False: ``mavlink:udp:...``, which only a
    provider's own check can explain)."""

    @classmethod
    def parse(cls, text: str) -> VehicleRef:
        """Read a ``backend:``. Raises ``ValueError`` (:data:`EXPECTED`) if it has not even
        the form :data:`BACKEND_RE`."""
        if not re.match(BACKEND_RE, text):
            raise ValueError(EXPECTED)
        head, colon, rest = text.partition(":")
        scheme, _, transport = head.partition("+")
        slashes = rest.startswith("//")
        return cls(text, scheme, transport, rest[2:] if slashes else rest, not colon or slashes)

    def __str__(self) -> str:
        return self.url


SIM = VehicleRef("sim", "sim")
"""The embedded simulator's reference (an agent's default ``backend:``)."""
