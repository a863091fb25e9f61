"""Exceptions of qpnso: one root class, one subclass per failure kind.

Every error qpnso raises on purpose derives from :class:`QpnsoError`, so a
caller can catch ``QpnsoError`` for "anything qpnso refused" or one subclass
for the failure it expects.  Errors about a bad argument also derive from
:class:`ValueError` so that code written against NumPy conventions still works.
"""

from __future__ import annotations


class QpnsoError(Exception):
    """Root of every error raised by qpnso."""


class InputError(QpnsoError, ValueError):
    """An argument has the wrong shape, contains NaN/inf, or is out of range."""


class JointLimitError(InputError):
    """A joint configuration lies outside the joint position limits."""


class RobotNotFoundError(QpnsoError, LookupError):
    """Unknown robot name, missing model file or optional robot package."""


class FrameNotFoundError(QpnsoError, LookupError):
    """A frame named by the user does not exist in the model."""


class ModelError(QpnsoError):
    """A robot model is malformed or not supported (e.g. unsupported joint)."""


class SingularityError(QpnsoError):
    """A quantity is undefined at this configuration (e.g. arm angle)."""


class UnreachableError(QpnsoError):
    """A tool pose cannot be reached by the arm (no IK solution)."""


class SolverError(QpnsoError):
    """A QP back end is unknown, not installed or failed to solve."""


class TrajectoryError(InputError):
    """A trajectory file or array is malformed."""


class ConfigError(InputError):
    """A configuration key or value is unknown or invalid."""


class JobError(QpnsoError):
    """A study job raised; the message names the study, the job index and the error."""
