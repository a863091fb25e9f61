"""A 3-D replay of a run, in the browser (docs/method.md §11; the optional extra ``view``: viser).

:mod:`.replay` reads what a replay shows (a result file or a scenario's simulation), :mod:`.geometry` computes
where each part is (Pinocchio's forward kinematics, the elbow circle), :mod:`.scene` draws it with viser: a live
server with a timeline, or one self-contained HTML page that plays the run.
"""

from qpnso.view.replay import Replay, load_replay, scenario_replay

__all__ = ["Replay", "load_replay", "scenario_replay"]
