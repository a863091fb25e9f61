"""The command line: each command runs end to end; bad input is one clear line."""

from __future__ import annotations

import numpy as np
import pytest

from qpnso.cli import main


def test_info_prints_model_and_costs(capsys) -> None:
    assert main(["info"]) == 0
    out = capsys.readouterr().out
    assert "robot lwr4p" in out and "joint_7" in out
    assert "friction_force" in out and "largest principal mass" in out


def test_info_accepts_degrees_and_another_robot(capsys) -> None:
    assert main(["info", "iiwa14", "--q-deg", "0,30,0,-60,0,45,0"]) == 0
    assert "[0.0, 30.0, 0.0, -60.0, 0.0, 45.0, 0.0] deg" in capsys.readouterr().out


@pytest.mark.parametrize("argv, message", [
    (["info", "ur5"], "unknown robot 'ur5'"),
    (["info", "--q", "0,0,0,3,0,0,0"], "outside its limits"),
    (["info", "--tool-frame", "nope"], "unknown tool frame"),
])
def test_info_errors_are_one_line(capsys, argv, message) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_bad_vector_is_a_usage_error(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["info", "--q", "0,0,nan,0,0,0,0"])
    assert exc.value.code == 2
    assert "NaN" in capsys.readouterr().err
