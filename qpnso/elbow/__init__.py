"""The elbow's geometry: the arm angle (:mod:`.arm_angle`) and the S-R-S closed forms (:mod:`.srs`), docs/method.md §4,
the joint-limit continuity intervals (:mod:`.intervals`, §5) and the range of motion with its stiffness
(:mod:`.rom`, §6)."""
