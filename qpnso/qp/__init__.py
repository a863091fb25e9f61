"""The hierarchical QP (docs/method.md §7): levels, the line fast path, the general cascade and its
back ends (:mod:`.hqp`)."""
