"""The robot model: the Pinocchio robot and its data (:mod:`.robot`), the same model in CasADi
(:mod:`.symbolic`), the costs felt at the tool with exact derivatives (:mod:`.costs`, docs/method.md §2–3)
and how CasADi functions are evaluated or compiled (:mod:`.codegen`)."""
