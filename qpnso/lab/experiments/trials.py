"""What the experiments share: the plant's model error, a subject per index, a trial's seeds, a trial run.

Seeds: an experiment run with ``seed`` draws subject ``s`` from ``job_rng(seed, SUBJECT_STREAM + s)``, so a
subject is the same person in every trial; a trial's force noise from its job's own generator; the plant's
model error once per experiment from ``seed`` (one robot for every subject and strategy, as in a lab).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

from qpnso.errors import QpnsoError
from qpnso.lab.parallel import job_rng
from qpnso.lab.plant import ModelMismatch
from qpnso.lab.surgeon import Subject

if TYPE_CHECKING:
    from qpnso.lab.simulation import SimulationConfig
    from qpnso.model.robot import Robot

SUBJECT_STREAM = 100_000
"""Offset of the subjects' random streams (job indices stay below it)."""
ORDER_STREAM = 200_000
"""Offset of the target orders' random streams."""

EXPERIMENT_MODEL_ERROR = {"mass": 0.1, "friction": 0.1, "armature": 0.2, "torque_offset": 0.2}
"""The plant's model error in the experiments (fixed before any result was seen; stated assumptions):
link masses and inertias 10 %, Coulomb friction 10 % (the mass/friction paper's N(0, (10 %)²)), rotor
inertias 20 %, joint torque offsets 0.2 N·m (torque-sensor bias).  What moves a real arm's null space."""

TRIAL_KEYS = (
    "user_work_per_metre_N",
    "user_work_per_nominal_metre_N",
    "path_length_m",
    "intended_path_length_m",
    "hand_work_J",
    "orthogonal_torque_mean_Nm",
    "elbow_mobility_deg",
    "constraint_proximity_deg",
    "rom_proximity_deg",
    "smoothness",
    "intended_smoothness",
    "mass_mean_kg",
    "mass_model_mean_kg",
    "friction_force_mean_N",
    "friction_model_mean_N",
    "tool_position_error_max_m",
    "status_not_ok_ticks",
    "duration_s",
)
"""The run summary's keys a trial row keeps (with the per-segment smoothness keys)."""
COLUMNS = {"user_work_per_metre_N": "work_per_metre", "user_work_per_nominal_metre_N": "work_per_nominal_metre"}
"""Summary keys a trial row names otherwise (``work_per_metre``, ``work_per_nominal_metre``: N = J/m, [M 24]
before normalisation, over the measured and over the intended path)."""


def model_error(seed: int, values: dict[str, float] | None = None) -> ModelMismatch:
    """The experiment's plant draw: :data:`EXPERIMENT_MODEL_ERROR` (or ``values``), seeded by ``seed``."""
    return ModelMismatch(**(EXPERIMENT_MODEL_ERROR if values is None else values), seed=int(seed))


@dataclass(frozen=True)
class PlantOptions:
    """What each experiment sets of its plant and robot: ``model_error`` (empty: :data:`EXPERIMENT_MODEL_ERROR`)
    and ``armature_kgm2``, the rotor inertia (kg·m², >= 0) on every joint, in the controller and the plant
    alike (None: the model's own, ``models/armature.json``)."""

    model_error: dict[str, float] = field(default_factory=dict)
    armature_kgm2: float | None = None

    def __post_init__(self) -> None:
        from qpnso.model.robot import checked_armature_kgm2

        checked_armature_kgm2(self.armature_kgm2)

    def load_robot(self, name: str) -> "Robot":
        """Robot ``name`` with the rotor inertia ``armature_kgm2``."""
        from qpnso.model.robot import load_robot_with_armature

        return load_robot_with_armature(name, self.armature_kgm2)

    def simulation(self, seed: int, index: int, person: Subject) -> "SimulationConfig":
        """Job ``index``'s simulation: ``person`` at the tool, the experiment's plant draw, the job's force noise."""
        from qpnso.lab.simulation import SimulationConfig

        return SimulationConfig(
            surgeon=person, model_error=model_error(seed, self.model_error or None), noise_seed=noise_seed(seed, index)
        )


def subject(seed: int, index: int) -> Subject:
    """Subject ``index`` of an experiment run with ``seed``."""
    return Subject.draw(job_rng(seed, SUBJECT_STREAM + index))


def noise_seed(seed: int, index: int) -> int:
    """The force-noise seed of job ``index``."""
    return int(job_rng(seed, index).integers(2**31))


def trial_row(summary: dict[str, Any] | None, error: str = "") -> dict[str, Any]:
    """A trial's row from its run summary (:data:`TRIAL_KEYS`, the per-segment smoothness), NaN where a
    value is missing; ``error`` says why a run stopped (its values are then NaN)."""
    s = summary or {}
    row: dict[str, Any] = {COLUMNS.get(k, k): float(s.get(k, math.nan)) for k in TRIAL_KEYS}
    row.update({k: float(v) for k, v in s.items() if k.startswith("smoothness_segment_")})
    row["error"] = error
    return row


def run_or_error(run) -> tuple[dict[str, Any] | None, str]:
    """``run()``'s summary, or None and the message of the :class:`QpnsoError` that stopped it (a joint
    driven past its limit: the trial is reported, not dropped)."""
    try:
        return run().summary, ""
    except QpnsoError as exc:
        return None, f"{type(exc).__name__}: {exc}"


def subject_record(s: Subject) -> dict[str, float]:
    """A subject's parameters for a trial row, prefixed ``subject_``."""
    return {f"subject_{k}": float(v) for k, v in asdict(s).items()}
