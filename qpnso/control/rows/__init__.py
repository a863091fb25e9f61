"""Constraint rows of the control tick under one contract (docs/method.md §7.2): a row kind says what
it keeps within bounds, ``h_lo ≤ h(q) ≤ h_hi``, and the tick turns it into the velocity row
``∇h(q)ᵀ q̇`` within the one velocity damper (:func:`~qpnso.control.rows.damper.damper`).

* :mod:`~qpnso.control.rows.damper` — the damper every row uses;
* :mod:`~qpnso.control.rows.joint_limits` — the joint limits (the QP's bounds);
* :mod:`~qpnso.control.rows.elbow` — the arm angle within ROM_t (the ``qp`` strategy's soft row);
* :mod:`~qpnso.control.rows.kind` — :class:`RowKind`, the contract a new row kind implements: its value
  ``h(q)`` as a CasADi expression (evaluated with its exact gradient in the tick's one CasADi call) and
  its bounds, hard or soft.  Adding a row kind is one file with one such class, given to
  ``ControllerConfig(rows=...)``.
"""

from qpnso.control.rows.kind import RowKind

__all__ = ["RowKind"]
