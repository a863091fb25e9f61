"""The studies' settings: :class:`StudyOptions`, read from a dict or the command line's strings."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any, Sequence

from qpnso.errors import ConfigError
from qpnso.model.robot import checked_armature_kgm2


# ------------------------------------------------------------------ options
@dataclass(frozen=True)
class StudyOptions:
    """Settings of the studies (each study stores the ones it uses in its checkpoint header).

    ``grid_step_deg``: arm-angle grid of the extremum search (deg);
    ``singular_threshold``: smallest admissible singular value of ``J Jᵀ``;
    ``mass_shares``: weights ``w`` of the trade-off (mass share, friction 1 − w);
    ``trials``, ``friction_sd``: uncertainty trials per pose and relative sd of
    ``tau_max``; ``duration_scale``: fraction of the scenario paths to run;
    ``compile``: CasADi evaluation mode of the workers (:mod:`qpnso.model.codegen`);
    ``armature_kgm2``: the rotor inertia (kg·m², >= 0) on every joint, None: the model's own
    (``models/armature.json``).
    """

    robot: str = "lwr4p"
    grid_step_deg: float = 1.0
    singular_threshold: float = 1e-4
    mass_shares: tuple[float, ...] = (0.9, 0.5, 0.1)
    trials: int = 100
    friction_sd: float = 0.10
    duration_scale: float = 1.0
    compile: str = "off"
    armature_kgm2: float | None = None

    def __post_init__(self) -> None:
        if not 0 < self.grid_step_deg <= 30:
            raise ConfigError(f"grid_step_deg must be in (0, 30], got {self.grid_step_deg}")
        if not self.singular_threshold >= 0:
            raise ConfigError(f"singular_threshold must be >= 0, got {self.singular_threshold}")
        if not self.mass_shares or any(not 0 <= w <= 1 for w in self.mass_shares):
            raise ConfigError(f"mass_shares must be weights in [0, 1], got {self.mass_shares}")
        if self.trials < 1 or not 0 <= self.friction_sd < 1:
            raise ConfigError(f"need trials >= 1 and 0 <= friction_sd < 1, got {self.trials}, {self.friction_sd}")
        checked_armature_kgm2(self.armature_kgm2)
        if not 0 < self.duration_scale <= 1:
            raise ConfigError(f"duration_scale must be in (0, 1], got {self.duration_scale}")

    @classmethod
    def from_dict(cls, values: dict[str, Any] | None) -> "StudyOptions":
        values = dict(values or {})
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(f"unknown study option(s) {unknown}; known: {sorted(known)}")
        defaults = cls()
        for key, value in values.items():
            values[key] = _coerce(key, value, getattr(defaults, key))
        return cls(**values)

    def subset(self, names: Sequence[str]) -> dict[str, Any]:
        data = asdict(self)
        return {k: list(data[k]) if isinstance(data[k], tuple) else data[k] for k in names}


def _coerce(key: str, value: Any, default: Any) -> Any:
    """``value`` converted to the type of the option's default (CLI strings accepted); an option whose default
    is None (``armature_kgm2``) takes a number, or None / ``"none"``."""
    try:
        if default is None:
            return None if value is None or str(value).lower() == "none" else float(value)
        if isinstance(default, tuple):
            items = value.split(",") if isinstance(value, str) else value
            return tuple(float(x) for x in items)
        if isinstance(default, (int, float)) and isinstance(value, str):
            return type(default)(float(value)) if isinstance(default, float) else int(value)
        return type(default)(value)
    except (TypeError, ValueError):
        raise ConfigError(f"study option {key}={value!r} is not a {type(default).__name__}") from None
