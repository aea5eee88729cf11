"""The root of btmission's exceptions.

Every exception class btmission defines derives from :class:`BtmissionError`, directly or through
another of btmission's exceptions (one deliberate exception: ``RunStopped``, see below), so
``except BtmissionError`` catches any error btmission raises on purpose (bad input, a failed
check, a refused command, a vehicle that cannot be reached ...) and lets everything else, a bug
included, through. tests/unit/base/test_errors.py holds every class to it. This module is the bottom of the
layers: it imports nothing from btmission, so every module can import it.
"""

from __future__ import annotations

__all__ = ["BtmissionError"]


class BtmissionError(Exception):
    """The root of every exception btmission raises on purpose.

    Catch it to catch any of btmission's own errors. Each subclass also keeps its standard base
    (:class:`ValueError`, :class:`LookupError`, :class:`OSError`, :class:`RuntimeError` ...), so
    existing ``except ValueError`` code keeps working: a
    :class:`~btmission.spec.costexpr.CostExprError` is both a ``BtmissionError`` and a
    ``ValueError``.

    One exception is deliberately outside it: :class:`btmission.runtime.session.RunStopped` is a
    :class:`BaseException` (like :class:`KeyboardInterrupt`) so that ``except Exception`` does
    not swallow a stop signal, and a ``BtmissionError`` is an ``Exception``.
    """
