"""Typed settings (qpnso/settings.py): every settings dataclass checks each value
against its field's type, then its range; a bad value is a ConfigError naming the
key (with its table path), the value and what was expected — through the API, a
config TOML, a scenario TOML and the command line."""

from __future__ import annotations

import dataclasses
import math
import pickle
import typing
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import settings as hsettings
from hypothesis import strategies as st

import qpnso
from qpnso.cli import main
from qpnso.control.config import ControllerConfig
from qpnso.control.offline import load_config
from qpnso.lab.scenarios import SCENARIO_DIR, load_scenario
from qpnso.lab.simulation import SimulationConfig
from qpnso.lab.surgeon import Subject
from qpnso.model.costs import CostWeights
from qpnso.qp import QPSettings

SETTINGS_CLASSES = (ControllerConfig, CostWeights, QPSettings, SimulationConfig, Subject)


# --------------------------------------------------------------- through the API
@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"dt": "0.001"}, "dt = '0.001': expected a finite number"),
        ({"qp_settings": {"warm_start": "no"}}, "qp_settings.warm_start = 'no': expected true or false"),
        ({"qp_settings": {"warm_start": 1}}, "qp_settings.warm_start = 1: expected true or false"),
        ({"interval_period": 2.5}, "interval_period = 2.5: expected an integer"),
        ({"interval_period": True}, "interval_period = True: expected an integer"),
        ({"pose_gain": float("inf")}, "pose_gain = inf: expected a finite number"),
        ({"pose_gain": 1j}, "pose_gain = 1j: expected a finite number"),
        ({"strategy": 3}, "strategy = 3: expected a string"),
        ({"stiffness_slope": "1"}, "stiffness_slope = '1': expected a finite number (int or float) or None"),
        ({"fixed_posture": [0.0, "a"]}, "fixed_posture = [0.0, 'a']: expected a list of finite numbers or None"),
        ({"weights": {"mass": "1"}}, "weights.mass = '1': expected a finite number"),
        ({"weights": 5}, "weights = 5: expected a table of CostWeights settings"),
        ({"qp_settings": {"max_iter": 2.5}}, "qp_settings.max_iter = 2.5: expected an integer"),
        ({"qp_settings": {"solver_options": []}}, "qp_settings.solver_options = []: expected a table"),
    ],
)
def test_wrong_types_name_key_value_and_type(kwargs, message) -> None:
    with pytest.raises(qpnso.ConfigError) as exc:
        ControllerConfig(**kwargs)
    assert message in str(exc.value)


def test_unknown_keys_are_listed_with_the_valid_ones() -> None:
    with pytest.raises(
        qpnso.ConfigError,
        match=r"weights: unknown key 'masss'; valid keys: friction_force, friction_torque, "
        r"inertia, mass$",
    ):
        ControllerConfig(weights={"masss": 1})
    with pytest.raises(qpnso.ConfigError, match=r"qp_settings: unknown key 'maxiter'; valid keys: ") as exc:
        ControllerConfig.from_dict({"qp_settings": {"maxiter": 3}})
    listed = str(exc.value).split("valid keys: ")[1].split(", ")
    assert listed == sorted(f.name for f in dataclasses.fields(QPSettings)) and "max_iter_active_set" in listed
    with pytest.raises(
        qpnso.ConfigError, match=r"unknown keys 'colour', 'shape'; valid keys: compile, cost_filter_time"
    ):
        ControllerConfig.from_dict({"shape": 1, "colour": "red"})
    with pytest.raises(
        qpnso.ConfigError, match=r"surgeon: unknown key 'stifness'; valid keys: correction_force_max, correction_rate, "
    ):
        SimulationConfig(surgeon={"stifness": 3.0})


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: ControllerConfig(dt=0.5), "dt = 0.5: must be in (0, 0.1] s"),
        (lambda: ControllerConfig(cost_filter_time=-1), "cost_filter_time = -1.0: must be >= 0"),
        (lambda: ControllerConfig(rom_half_width_deg=0), "rom_half_width_deg = 0.0: must be > 0"),
        (lambda: ControllerConfig(safety_margin_deg=-2), "safety_margin_deg = -2.0: must be >= 0"),
        (lambda: ControllerConfig(interval_period=0), "interval_period = 0: must be >= 1"),
        (lambda: ControllerConfig(joint_limit_gain=2000), "joint_limit_gain = 2000.0: must be <= 1/dt = 1000"),
        (lambda: ControllerConfig(q_limit_tolerance_deg=-0.1), "q_limit_tolerance_deg = -0.1: must be >= 0"),
        (lambda: ControllerConfig(recovery_speed=0), "recovery_speed = 0.0: must be > 0"),
        (lambda: ControllerConfig(dq_tolerance_factor=0.9), "dq_tolerance_factor = 0.9: must be >= 1"),
        (lambda: ControllerConfig(weights={"mass": -1}), "weights.mass = -1.0: cost weight must be >= 0"),
        (lambda: CostWeights(mass=-1), "CostWeights: mass = -1.0: cost weight must be >= 0"),
        (lambda: QPSettings(max_iter_active_set=0), "QPSettings: max_iter_active_set = 0: must be > 0"),
        (lambda: QPSettings(max_iter=0), "max_iter = 0: must be > 0"),
        (lambda: QPSettings(regularization=-1e-3), "regularization = -0.001: must be >= 0 or None"),
        (lambda: SimulationConfig(timestep=0), "timestep = 0.0: must be > 0 s"),
        (lambda: SimulationConfig(model_error={"mass": -1}), "model_error.mass = -1.0: must be >= 0"),
        (lambda: SimulationConfig(surgeon={"damping": -1}), "surgeon.damping = -1.0: must be >= 0"),
        (lambda: Subject(stiffness="600"), "stiffness = '600': expected a finite number"),
        (lambda: SimulationConfig(noise_seed=2.5), "noise_seed = 2.5: expected an integer"),
    ],
)
def test_range_errors_name_key_value_and_range(make, message) -> None:
    with pytest.raises(qpnso.ConfigError) as exc:
        make()
    assert message in str(exc.value)


def test_new_settings_have_documented_defaults() -> None:
    cfg = ControllerConfig()
    assert (cfg.q_limit_tolerance_deg, cfg.recovery_speed, cfg.dq_tolerance_factor) == (2.0, 0.2, 5.0)
    assert QPSettings().max_iter_active_set == 1000
    assert ControllerConfig(q_limit_tolerance_deg=0, dq_tolerance_factor=1).q_limit_tolerance_deg == 0.0


def test_numpy_scalars_are_numbers_and_errors_show_plain_values() -> None:
    cfg = ControllerConfig(
        dt=np.float64(0.002),
        interval_period=np.int64(5),
        fixed_posture=np.zeros(7),
        weights={"mass": np.float32(0.5)},
        qp_settings={"max_iter": np.int32(50), "max_iter_active_set": np.int64(50), "warm_start": np.bool_(False)},
    )
    assert type(cfg.dt) is float and cfg.dt == 0.002
    assert type(cfg.interval_period) is int and cfg.interval_period == 5
    assert cfg.qp_settings.warm_start is False
    assert cfg.fixed_posture == (0.0,) * 7 and all(type(x) is float for x in cfg.fixed_posture)
    assert type(cfg.weights.mass) is float and type(cfg.qp_settings.max_iter) is int
    with pytest.raises(qpnso.ConfigError) as exc:
        ControllerConfig(dt=np.float64(0.5))
    assert "dt = 0.5: must be in (0, 0.1] s" in str(exc.value) and "np." not in str(exc.value)
    with pytest.raises(qpnso.ConfigError) as exc:
        ControllerConfig(interval_period=np.float64(2.5))
    assert "interval_period = 2.5: expected an integer" in str(exc.value)


def test_dict_round_trip_and_nested_dicts() -> None:
    cfg = ControllerConfig(
        strategy="rom",
        weights={"mass": 1},
        fixed_posture=[0.1] * 7,
        recovery_speed=0.3,
        q_limit_tolerance_deg=1.0,
        dq_tolerance_factor=2.0,
        qp_settings=QPSettings(max_iter_active_set=50, solver_options={"verbose": False}),
    )
    assert cfg.weights == CostWeights(mass=1.0) and isinstance(cfg.weights.mass, float)
    assert ControllerConfig.from_dict(cfg.to_dict()) == cfg
    assert ControllerConfig(weights={"mass": 1}).weights == CostWeights(mass=1.0)
    assert SimulationConfig.from_dict({"surgeon": {"stiffness": 100}}).surgeon.stiffness == 100.0
    assert QPSettings.from_dict({"max_iter_active_set": 20}).max_iter_active_set == 20
    assert CostWeights.from_dict({"mass": 0}).mass == 0.0


def test_setting_errors_survive_pickling() -> None:
    """A study worker's error crosses a process boundary."""
    with pytest.raises(qpnso.ConfigError) as exc:
        ControllerConfig(weights={"mass": "1"})
    again = pickle.loads(pickle.dumps(exc.value))
    assert type(again) is type(exc.value) and str(again) == str(exc.value) and again.key == "weights.mass"


# ------------------------------------------------------------------ hypothesis
def _wrong(hint: typing.Any, value: typing.Any) -> bool:
    """Independent statement of what each type hint refuses (module doc of qpnso.settings)."""
    if isinstance(value, np.generic):
        value = value.item()
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is not None and type(None) in args:  # X | None, X | Y | None: wrong for every arm
        return value is not None and all(_wrong(a, value) for a in args if a is not type(None))
    if origin is tuple:
        return (
            not isinstance(value, (list, tuple))
            and not (isinstance(value, np.ndarray) and value.ndim == 1)
            or any(_wrong(args[0], v) for v in value)
        )
    if dataclasses.is_dataclass(hint):
        return not isinstance(value, (hint, dict))
    if hint is float:
        return type(value) not in (int, float) or not math.isfinite(value)
    return type(value) is not hint


_ANY = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(),
    st.floats(),
    st.complex_numbers(),
    st.text(max_size=4),
    st.binary(max_size=4),
    st.lists(st.one_of(st.floats(), st.text(max_size=2)), max_size=3),
    st.tuples(st.integers()),
    st.dictionaries(st.text(max_size=4), st.integers(-3, 3), max_size=2),
    st.floats(allow_nan=False, allow_infinity=False).map(np.float64),
    st.integers(-10, 10).map(np.int64),
    st.booleans().map(np.bool_),
)
_FIELDS = [(cls, name, hint) for cls in SETTINGS_CLASSES for name, hint in typing.get_type_hints(cls).items()]


@hsettings(max_examples=400, deadline=None)
@given(field=st.sampled_from(_FIELDS), value=_ANY)
def test_any_value_gives_a_config_or_a_config_error_never_a_type_error(field, value) -> None:
    cls, name, hint = field
    try:
        obj = cls(**{name: value})
    except qpnso.ConfigError as exc:
        assert name in str(exc) and "np." not in str(exc)
        return
    assert not _wrong(hint, value), f"{cls.__name__}.{name} accepted {value!r}"
    stored = getattr(obj, name)
    assert not isinstance(stored, np.generic)
    if hint is float:
        assert type(stored) is float


@hsettings(max_examples=200, deadline=None)
@given(
    field=st.sampled_from([f for f in _FIELDS if f[2] in (float, int, bool)]),
    value=st.one_of(st.text(), st.binary(), st.complex_numbers(), st.lists(st.integers()), st.none()),
)
def test_wrong_typed_numbers_and_flags_always_name_the_key(field, value) -> None:
    cls, name, _ = field
    with pytest.raises(qpnso.ConfigError) as exc:
        cls(**{name: value})
    assert f"{name} = " in str(exc.value) and "expected" in str(exc.value)


# ------------------------------------------------------------- config TOML file
@pytest.mark.parametrize(
    "text, message",
    [
        ('dt = "0.001"\n', "dt = '0.001': expected a finite number"),
        ('[controller]\ndt = "0.001"\n', "dt = '0.001': expected a finite number"),
        ('[controller.qp_settings]\nwarm_start = "no"\n', "qp_settings.warm_start = 'no': expected true or false"),
        ("[controller]\ninterval_period = 2.5\n", "interval_period = 2.5: expected an integer"),
        ('[controller.weights]\nmass = "1"\n', "weights.mass = '1': expected a finite number"),
        (
            "[weights]\nmasss = 1\n",
            "weights: unknown key 'masss'; valid keys: friction_force, friction_torque, inertia, mass",
        ),
        ("[controller.qp_settings]\nmax_iter = 2.5\n", "qp_settings.max_iter = 2.5: expected an integer"),
        ("[controller.qp_settings]\nmax_iter_active_set = 0\n", "qp_settings.max_iter_active_set = 0: must be > 0"),
        ("[controller]\nq_limit_tolerance_deg = -1\n", "q_limit_tolerance_deg = -1.0: must be >= 0"),
        ("[controller]\nrecovery_speed = 0\n", "recovery_speed = 0.0: must be > 0"),
        ("[controller]\ndq_tolerance_factor = 0.5\n", "dq_tolerance_factor = 0.5: must be >= 1"),
        ("[controller]\ndt = 5\n", "dt = 5.0: must be in (0, 0.1] s"),
        (
            'strategy = "damped"\n[controller]\ndt = 0.001\n',
            "strategy: not allowed at the top level beside a [controller] table",
        ),
        (
            'strategy = "damped"\n[controller]\nstrategy = "qp"\n',
            "strategy: given both at the top level and under [controller]",
        ),
        ("[weights]\nmass = 2\n[controller]\ndt = 0.001\n", "weights: not allowed at the top level"),
        ("colour = 1\n[controller]\n", "colour: not allowed at the top level"),
        ("controller = 5\n", "controller = 5: expected a table"),
    ],
)
def test_config_file_errors_name_the_file_and_the_key(tmp_path, text, message) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    with pytest.raises(qpnso.ConfigError) as exc:
        load_config(bad)
    assert str(exc.value).startswith(f"{bad}: ") and message in str(exc.value)


def test_config_file_layouts_still_load(tmp_path) -> None:
    """Top level, [controller], and a scenario file (its other tables are allowed) as a config file;
    a flag overriding a bad file value wins, a bad flag is not blamed on the file."""
    top, nested = tmp_path / "top.toml", tmp_path / "nested.toml"
    top.write_text('strategy = "rom"\nrecovery_speed = 0.5\n[weights]\nmass = 2\n')
    nested.write_text('[controller]\nstrategy = "rom"\nrecovery_speed = 0.5\n[controller.weights]\nmass = 2\n')
    for path in (top, nested):
        cfg = load_config(path)
        assert (cfg.strategy, cfg.recovery_speed, cfg.weights.mass) == ("rom", 0.5, 2.0)
    cfg = load_config(SCENARIO_DIR / "B.toml", {"dt": None})
    assert cfg.rom_half_width_deg == 10.0 and cfg.dq_tolerance_factor == 5.0
    bad_dt = tmp_path / "dt.toml"
    bad_dt.write_text("[controller]\ndt = 5\n")
    assert load_config(bad_dt, {"dt": 0.002}).dt == 0.002
    with pytest.raises(qpnso.ConfigError) as exc:
        load_config(top, {"dt": 0.5})
    assert "dt = 0.5: must be in (0, 0.1] s" in str(exc.value) and str(top) not in str(exc.value)


# ----------------------------------------------------------- scenario TOML file
def _scenario(tmp_path: Path, old: str, new: str) -> Path:
    text = (SCENARIO_DIR / "A.toml").read_text()
    assert old in text
    path = tmp_path / "s.toml"
    path.write_text(text.replace(old, new))
    return path


@pytest.mark.parametrize(
    "old, new, message",
    [
        ("ns0_deg = 0.0", 'ns0_deg = "zero"', "start.ns0_deg = 'zero': expected a finite number"),
        ("branch = [-1, 1, -1]", "branch = [-1, 1]", "start.branch = [-1, 1]: expected a list of 3 integers"),
        ("branch = [-1, 1, -1]", "branch = [-1, 2, -1]", "start.branch = (-1, 2, -1): must be three signs"),
        ('name = "A"', "name = 1", "scenario.name = 1: expected a string"),
        (
            "size = 0.08",
            "size = 0.08\ncolour = 1",
            "path: unknown key 'colour'; valid keys: duration, kind, size, speed",
        ),
        ("size = 0.08", "size = -0.08", "path.size = -0.08: must be > 0"),
        ('kind = "guidance"', 'kind = "circle"', "path.kind = 'circle': must be 'guidance' or 'hold'"),
        ("cost_filter_time = 0.3", 'cost_filter_time = "0.3"', "controller.cost_filter_time = '0.3': expected"),
        (
            "cost_filter_time = 0.3",
            "cost_filter_time = 0.3\nmasss = 1",
            "controller: unknown key 'masss'; valid keys: ",
        ),
        (
            "cost_filter_time = 0.3",
            "cost_filter_time = 0.3\ninterval_period = 2.5",
            "controller.interval_period = 2.5: expected an integer",
        ),
        ("[path]", "[paths]\n[path]", "unknown key 'paths'; valid keys: controller, obstacles, path, scenario, start"),
    ],
)
def test_scenario_file_errors_name_the_file_and_the_key(tmp_path, old, new, message) -> None:
    bad = _scenario(tmp_path, old, new)
    with pytest.raises(qpnso.ConfigError) as exc:
        load_scenario(bad)
    assert str(exc.value).startswith(f"{bad}: ") and message in str(exc.value)


# ----------------------------------------------------------------- command line
@pytest.mark.parametrize("command", ["solve", "simulate"])
def test_cli_bad_config_is_one_error_line_naming_the_key(tmp_path, capsys, command) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[controller.weights]\nmass = "1"\n')
    out = tmp_path / "out"
    if command == "solve":
        csv = tmp_path / "hold.csv"
        assert (
            main(
                [
                    "trajectory",
                    "hold",
                    "--center",
                    "0.65,0,0.5",
                    "--rpy-deg",
                    "180,30,180",
                    "--duration",
                    "0.05",
                    "--out",
                    str(csv),
                ]
            )
            == 0
        )
        argv = ["solve", str(csv), "--config", str(bad), "--out", str(out / "r.npz"), "--quiet"]
    else:
        argv = ["simulate", "--scenario", "A", "--config", str(bad), "--out", str(out), "--quiet", "--no-plot"]
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("qpnso: error: ")
    assert f"{bad}: weights.mass = '1': expected a finite number" in err
    assert not out.exists()
