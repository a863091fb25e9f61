"""The control tick (docs/method.md §7–8): :class:`~qpnso.control.controller.Controller`, its
settings and outputs (:mod:`.config`), the arm's state in one CasADi call (:mod:`.state`), the
compiled tick (:mod:`.tick`), the strategies (:mod:`.strategies`), and the offline solve of a
tool trajectory (:mod:`.offline`, :mod:`.trajectory`)."""
