"""Errors a mission's fusion client raises for the mission loop to act on."""

from __future__ import annotations

__all__ = ["PreconditionFailed"]


class PreconditionFailed(Exception):
    """The fusion side refused a call because of its state (for a delta push: it does not hold the delta's base).
    The mission then uploads the full subset. The gRPC client's ``FailedPrecondition`` is one."""
