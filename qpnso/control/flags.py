"""The tick's status bits, defined once: the Numba kernels (:mod:`qpnso.control.tick`,
:mod:`qpnso.control.state`) set these integers, and :class:`qpnso.control.config.Status` names them for
users (``Command.status``)."""

FLAG_QP_FAILED = 1  # a QP level failed: safe fallback command
FLAG_ELBOW_DROPPED = 2  # arm angle singular: elbow constraints dropped
FLAG_ELBOW_SLACK = 4  # elbow bounds not met this tick: moving back
FLAG_ROM_EMPTY = 8  # ROM ∩ interval (with margin) empty: the nearest point kept
FLAG_Q_OUT_OF_LIMITS = 16  # q outside its limits: velocity bounds push it back
FLAG_INTERVAL_STALE = 32  # the continuity interval could not be updated
FLAG_TOOL_LIMITED = 64  # level 1 residual not zero (bounds or singularity)
FLAG_COST_UNDEFINED = 128  # the cost or its gradient is not finite here: no cost step
FLAG_TORQUE_SATURATED = 256  # τ clipped to the model's effort limits
FLAG_QP_FALLBACK = 512  # ProxQP did not solve within its iteration budget: DAQP answered
FLAG_ELBOW_OUTSIDE_ROM = 1024  # the arm angle is outside ROM_t this tick
FLAG_INTERNAL_ERROR = 2048  # a tick could not be computed: joints brought to rest at ddq_max, τ = g(q)
FLAG_QP_DEADLINE = 4096  # the cascade's time budget was spent: lower levels skipped (with QP_FAILED)
FLAG_OBSTACLE = 8192  # a link inside its margin of an obstacle (or overlapping it), or unable to keep its margin

PREDICTION_MISSED = 1 << 30  # not a status (no FLAG_): q̇ far from the predicted one, the tick is solved again

ELBOW_BITS = FLAG_INTERVAL_STALE | FLAG_ROM_EMPTY  # the elbow bookkeeping's own bits
