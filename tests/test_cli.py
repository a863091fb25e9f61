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


def test_intervals_writes_a_png(tmp_path, capsys) -> None:
    out = tmp_path / "iv.png"
    assert main(["intervals", "--q-deg", "0,30,0,-60,0,45,0", "--out", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "continuity interval" in capsys.readouterr().out


def test_trajectory_solve_plot_pipeline(tmp_path, capsys) -> None:
    csv = tmp_path / "hold.csv"
    assert main(["trajectory", "hold", "--center", "0.65,0,0.5", "--rpy-deg", "180,30,180",
                 "--duration", "0.2", "--out", str(csv)]) == 0
    res, summary = tmp_path / "r.npz", tmp_path / "s.json"
    assert main(["solve", str(csv), "--out", str(res), "--summary", str(summary), "--quiet",
                 "--strategy", "damped"]) == 0
    out = capsys.readouterr().out
    assert "strategy damped" in out and "tool_position_error_max_m" in out
    import json
    data = json.loads(summary.read_text())
    assert data["strategy"] == "damped" and data["ticks"] == 201
    fig = tmp_path / "r.png"
    assert main(["plot", str(res), "--out", str(fig)]) == 0
    assert fig.stat().st_size > 10_000


@pytest.mark.parametrize("content, message", [
    ("t,x,y,z,qx,qy,qz\n0,0,0,0,0,0,0\n", "qw"),
    ("t,x,y,z,qx,qy,qz,qw\n0,0.6,0,0.5,1,0,0,0\n0,0.6,0,0.5,1,0,0,0\n", "row 2"),
    ("t,x,y,z,qx,qy,qz,qw\n0,0.6,0,0.5,1,0,0,0\n1,nan,0,0.5,1,0,0,0\n", "row 2"),
    ("t,x,y,z,qx,qy,qz,qw\n0,0.6,0,0.5,1,0,0,0\n1,0.6,0,0.5,2,0,0,0\n", "row 2"),
])
def test_solve_rejects_malformed_csv_without_output(tmp_path, capsys, content, message) -> None:
    csv = tmp_path / "bad.csv"
    csv.write_text(content)
    res = tmp_path / "r.npz"
    assert main(["solve", str(csv), "--out", str(res), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not res.exists()


def test_solve_rejects_unknown_strategy_and_config_key(tmp_path, capsys) -> None:
    csv = tmp_path / "hold.csv"
    main(["trajectory", "hold", "--center", "0.65,0,0.5", "--rpy-deg", "180,30,180", "--duration", "0.05",
          "--out", str(csv)])
    assert main(["solve", str(csv), "--strategy", "magic", "--out", str(tmp_path / "r.npz"), "--quiet"]) == 2
    assert "unknown strategy 'magic'" in capsys.readouterr().err
    cfg = tmp_path / "c.toml"
    cfg.write_text("[controller]\nstiffnes_max = 3\n")
    assert main(["solve", str(csv), "--config", str(cfg), "--out", str(tmp_path / "r.npz"), "--quiet"]) == 2
    assert "stiffnes_max" in capsys.readouterr().err
    assert not (tmp_path / "r.npz").exists()


def test_solve_rejects_an_unreachable_trajectory(tmp_path, capsys) -> None:
    csv = tmp_path / "far.csv"
    main(["trajectory", "hold", "--center", "2,0,0.5", "--duration", "0.05", "--out", str(csv)])
    assert main(["solve", str(csv), "--out", str(tmp_path / "r.npz"), "--quiet"]) == 2
    assert "reach" in capsys.readouterr().err


def test_simulate_and_compare(tmp_path, capsys) -> None:
    out = tmp_path / "sim"
    assert main(["simulate", "--scenario", "A", "--strategy", "qp", "--duration-scale", "0.01",
                 "--out", str(out), "--quiet"]) == 0
    assert {p.name for p in out.iterdir()} == {"result.npz", "summary.json", "run.png"}
    cmp_out = tmp_path / "cmp"
    assert main(["compare", "--scenario", "B", "--strategies", "qp,damped", "--duration-scale", "0.01",
                 "--out", str(cmp_out), "--quiet"]) == 0
    table = (cmp_out / "comparison.md").read_text()
    assert "| qp |" in table and "| damped |" in table
    assert (cmp_out / "comparison.png").stat().st_size > 10_000


def test_plot_rejects_a_foreign_file(tmp_path, capsys) -> None:
    bad = tmp_path / "x.npz"
    np.savez(bad, a=np.zeros(3))
    assert main(["plot", str(bad), "--out", str(tmp_path / "x.png")]) == 2
    assert "not a qpnso result file" in capsys.readouterr().err


@pytest.mark.parametrize("what", ["cost", "interval", "tick"])
def test_bench_prints_median_and_p99(capsys, what) -> None:
    argv = ["bench", what, "-n", "20"] + (["--strategies", "qp,damped"] if what == "tick" else [])
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "| median µs | p99 µs |" in out
    rows = [line for line in out.splitlines() if line.startswith("| ") and "µs" not in line and "---" not in line]
    assert rows and all(float(r.split("|")[2]) > 0 for r in rows)
