"""The command line: each command runs end to end; bad input is one clear line."""

from __future__ import annotations

import json
import re
import sys

import numpy as np
import pytest
from conftest import SOURCE_TREE

from qpnso.cli import main


def test_info_prints_model_and_costs(capsys) -> None:
    assert main(["info"]) == 0
    out = capsys.readouterr().out
    assert "robot lwr4p" in out and "joint_7" in out
    assert "friction_force" in out and "largest principal mass" in out


def test_info_accepts_degrees_and_another_robot(capsys) -> None:
    assert main(["info", "iiwa14", "--q-deg", "0,30,0,-60,0,45,0"]) == 0
    assert "[0.0, 30.0, 0.0, -60.0, 0.0, 45.0, 0.0] deg" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, message",
    [
        (["info", "ur5"], "unknown robot 'ur5'"),
        (["info", "--q", "0,0,0,3,0,0,0"], "outside its limits"),
        (["info", "--tool-frame", "nope"], "unknown tool frame"),
    ],
)
def test_info_errors_are_one_line(capsys, argv, message) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_bad_vector_is_a_usage_error(capsys) -> None:
    assert main(["info", "--q", "0,0,nan,0,0,0,0"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("qpnso: error: --q contains NaN") and err.count("\n") == 1


def test_intervals_writes_a_png(tmp_path, capsys) -> None:
    out = tmp_path / "iv.png"
    assert main(["intervals", "--q-deg", "0,30,0,-60,0,45,0", "--out", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "continuity interval" in capsys.readouterr().out


def test_trajectory_solve_plot_pipeline(tmp_path, capsys) -> None:
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
                "0.2",
                "--out",
                str(csv),
            ]
        )
        == 0
    )
    res, summary = tmp_path / "r.npz", tmp_path / "s.json"
    assert (
        main(["solve", str(csv), "--out", str(res), "--summary", str(summary), "--quiet", "--strategy", "damped"]) == 0
    )
    out = capsys.readouterr().out
    assert "strategy damped" in out and "tool_position_error_max_m" in out
    import json

    data = json.loads(summary.read_text())
    assert data["strategy"] == "damped" and data["ticks"] == 201
    fig = tmp_path / "r.png"
    assert main(["plot", str(res), "--out", str(fig)]) == 0
    assert fig.stat().st_size > 10_000


@pytest.mark.parametrize(
    "content, message",
    [
        ("t,x,y,z,qx,qy,qz\n0,0,0,0,0,0,0\n", "qw"),
        ("t,x,y,z,qx,qy,qz,qw\n0,0.6,0,0.5,1,0,0,0\n0,0.6,0,0.5,1,0,0,0\n", "row 2"),
        ("t,x,y,z,qx,qy,qz,qw\n0,0.6,0,0.5,1,0,0,0\n1,nan,0,0.5,1,0,0,0\n", "row 2"),
        ("t,x,y,z,qx,qy,qz,qw\n0,0.6,0,0.5,1,0,0,0\n1,0.6,0,0.5,2,0,0,0\n", "row 2"),
    ],
)
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
    assert (
        main(
            [
                "simulate",
                "--scenario",
                "A",
                "--strategy",
                "qp",
                "--duration-scale",
                "0.01",
                "--out",
                str(out),
                "--quiet",
            ]
        )
        == 0
    )
    assert {p.name for p in out.iterdir()} == {"result.npz", "summary.json", "run.png"}
    cmp_out = tmp_path / "cmp"
    assert (
        main(
            [
                "compare",
                "--scenario",
                "B",
                "--strategies",
                "qp,damped",
                "--duration-scale",
                "0.01",
                "--out",
                str(cmp_out),
                "--quiet",
            ]
        )
        == 0
    )
    table = (cmp_out / "comparison.md").read_text()
    assert "| qp |" in table and "| damped |" in table
    assert (cmp_out / "comparison.png").stat().st_size > 10_000


def test_plot_rejects_a_foreign_file(tmp_path, capsys) -> None:
    bad = tmp_path / "x.npz"
    np.savez(bad, a=np.zeros(3))
    assert main(["plot", str(bad), "--out", str(tmp_path / "x.png")]) == 2
    assert "is not a qpnso result .npz" in capsys.readouterr().err


@pytest.mark.parametrize("what", ["cost", "interval", "tick"])
def test_bench_prints_median_and_tails(capsys, what) -> None:
    """Every row has a median, p95, p99 and p99.9 in order; ``tick`` times each strategy held and moving."""
    argv = ["bench", what, "-n", "20"] + (["--strategies", "qp,damped"] if what == "tick" else [])
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "| median µs | p95 µs | p99 µs | p99.9 µs |" in out
    rows = [line for line in out.splitlines() if line.startswith("| ") and "µs" not in line and "---" not in line]
    values = [[float(x) for x in r.split("|")[2:6]] for r in rows]
    assert rows and all(0 < a <= b <= c <= d for a, b, c, d in values)
    if what == "tick":
        for strategy in ("qp", "damped"):
            assert sum(f"strategy {strategy}, tool " in r and "obstacles" not in r for r in rows) == 2
        assert sum("strategy qp, tool held, 4 obstacles" in r for r in rows) == 1  # (the keep-out rows' cost)


# ------------------------------------------------------------------- issue 13, items 7 and 12
ROW = "{t:.2f},{x:.6g},0,0.5,4.329780281e-17,0.9659258263,4.329780281e-17,0.2588190451\n"
"""A held tool pose of examples/trajectories/hold_lwr4p.csv (rpy 180, 30, 180 deg), x in metres."""


def jump_csv(path, rows: int = 121, jump_row: int = 100, jump_m: float = 0.02) -> list[float]:
    """A 10 ms hold at x = 0.65 m whose x jumps by ``jump_m`` from data row ``jump_row`` (1-based) on (1 m: the
    spline asks up to 2.3 m/s, accepted; 2 m: 232 m/s, beyond ``tool_speed_accepted``)."""
    times = [0.01 * i for i in range(rows)]
    path.write_text(
        "t,x,y,z,qx,qy,qz,qw\n"
        + "".join(ROW.format(t=t, x=0.65 + (jump_m if i + 1 >= jump_row else 0.0)) for i, t in enumerate(times))
    )
    return times


def test_a_trajectory_faster_than_the_accepted_tool_speed_is_refused_naming_its_row(tmp_path, capsys) -> None:
    """Issue 31 item 6: a twist of 1e6 m/s was chased at the velocity limits; a trajectory that asks the tool more
    than ``tool_speed_accepted`` is refused before the run, naming the time and data row (one line, exit 2)."""
    csv = tmp_path / "jump.csv"
    jump_csv(csv, jump_m=2.0)
    assert main(["solve", str(csv), "--out", str(tmp_path / "r.npz"), "--quiet", "--dt", "0.004"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err
    assert "m/s" in err and "data row 9" in err and "tool_speed_accepted" in err


def test_solve_fails_when_the_tool_leaves_the_path(tmp_path, capsys) -> None:
    """Item 7: a 2 cm jump in x at data row 100 used to exit 0; now exit 1, naming the first row."""
    csv = tmp_path / "jump.csv"
    times = jump_csv(csv)
    res, summary = tmp_path / "r.npz", tmp_path / "s.json"
    assert main(["solve", str(csv), "--out", str(res), "--summary", str(summary), "--quiet", "--dt", "0.004"]) == 1
    captured = capsys.readouterr()
    line = captured.err.strip()
    assert line.startswith("qpnso: failed:") and "\n" not in line and "Traceback" not in captured.err
    data = json.loads(summary.read_text())  # the complete result is written all the same
    assert data["result"] == "failed"
    with np.load(res) as arrays:
        t, pos, rot = arrays["t"], arrays["tool_position_error"], arrays["tool_rotation_error"]
    assert len(t) == data["ticks"] == 301
    # the first tick out of tolerance, found here independently, and the CSV row at or before it
    k = int(np.flatnonzero((pos > 1e-3) | (rot > np.radians(1)))[0])
    row = sum(1 for x in times if x <= t[k] + 1e-9)
    assert data["first_failed_tick"] == k and data["first_failed_data_row"] == row
    assert data["first_failed_data_row_t_s"] == pytest.approx(times[row - 1])
    assert 90 <= row <= 100  # at the jump (the cubic spline starts moving a few rows early)
    assert f"data row {row} " in line and "data rows count from 1 after the header" in line
    assert data["tool_position_error_max_m"] > 0.01 and data["worst_position_error_m"] > 0.01  # (of the 2 cm jump)
    assert data["worst_position_error_data_row"] >= 100
    assert data["slow_ticks"] >= 0 and data["tick_time_max_ms"] > 0
    assert "result" in captured.out and "failed" in captured.out


def test_solve_tool_tolerance_flags(tmp_path, capsys) -> None:
    """A generous tolerance passes the same jump; a non-positive one is a one-line usage error."""
    csv = tmp_path / "jump.csv"
    jump_csv(csv, rows=41, jump_row=30)
    summary = tmp_path / "s.json"
    argv = ["solve", str(csv), "--out", str(tmp_path / "r.npz"), "--summary", str(summary), "--quiet", "--dt", "0.005"]
    assert main([*argv, "--tool-tolerance-mm", "5000", "--tool-tolerance-deg", "90"]) == 0
    data = json.loads(summary.read_text())
    assert data["result"] == "ok" and data["tool_tolerance_m"] == 5.0 and data["tool_tolerance_deg"] == 90.0
    capsys.readouterr()
    assert main([*argv, "--tool-tolerance-mm", "0"]) == 2
    assert capsys.readouterr().err == "qpnso: error: --tool-tolerance-mm must be a positive number, got 0\n"


def test_solve_ok_run_says_ok(tmp_path, capsys) -> None:
    csv = tmp_path / "hold.csv"
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
    summary = tmp_path / "s.json"
    assert main(["solve", str(csv), "--out", str(tmp_path / "r.npz"), "--summary", str(summary), "--quiet"]) == 0
    data = json.loads(summary.read_text())
    assert data["result"] == "ok" and "first_failed_data_row" not in data
    assert isinstance(data["slow_ticks"], float) and data["tick_time_max_ms"] == pytest.approx(
        data["tick_time_max_us"] / 1000
    )
    assert "qpnso: failed" not in capsys.readouterr().err


def test_bad_q0_is_one_line_naming_it(tmp_path, capsys) -> None:
    """Item 12: a bad --q0 printed the top-level usage; now one line naming --q0."""
    csv = tmp_path / "hold.csv"
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
    capsys.readouterr()
    for q0, message in (
        ("0,1,2", "--q0 needs 7 comma-separated numbers, got 3"),
        ("0,a,0,0,0,0,0", "--q0 must be comma-separated numbers"),
    ):
        assert main(["solve", str(csv), "--q0", q0, "--out", str(tmp_path / "r.npz"), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"qpnso: error: {message}") and err.count("\n") == 1 and "usage" not in err
    assert not (tmp_path / "r.npz").exists()


def test_trajectory_error_shows_plain_numbers(tmp_path, capsys) -> None:
    """Item 12: "t=np.float64(0.08)" in the repeated-time message; now "t=0.08"."""
    csv = tmp_path / "rep.csv"
    csv.write_text("t,x,y,z,qx,qy,qz,qw\n0,0.6,0,0.5,1,0,0,0\n0.08,0.6,0,0.5,1,0,0,0\n0.08,0.6,0,0.5,1,0,0,0\n")
    assert main(["solve", str(csv), "--out", str(tmp_path / "r.npz"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "data row 3 (t=0.08) repeats data row 2 (t=0.08)" in err and "np." not in err


def six_dof_urdf(tmp_path):
    """The shipped LWR4+ without joint 7 and link 7 (the flange moved onto link 6): a 6-DOF arm."""
    from qpnso.model.robot import MODELS_DIR

    text = (MODELS_DIR / "lwr4p.urdf").read_text()
    text = re.sub(r'\s*<joint name="joint_7".*?</joint>', "", text, flags=re.S)
    text = re.sub(r'\s*<link name="link_7">.*?</link>', "", text, flags=re.S)
    text = text.replace('<parent link="link_7"/>', '<parent link="link_6"/>')
    path = tmp_path / "arm6.urdf"
    path.write_text(text)
    return path


def test_six_dof_arm_is_refused_by_name(tmp_path, capsys) -> None:
    """Item 12: a 6-DOF URDF gave "no configuration reaches the first pose"; now it names the 7-DOF need."""
    urdf = six_dof_urdf(tmp_path)
    assert main(["info", str(urdf)]) == 0  # describing the model is fine
    assert "nq = 6" in capsys.readouterr().out
    expected = (
        "qpnso: error: qpnso needs a 7-DOF arm (one redundant degree of freedom for a 6-D tool task); "
        "arm6 has 6 joints\n"
    )
    for argv in (
        [
            "solve",
            str(SOURCE_TREE / "examples" / "trajectories" / "hold_lwr4p.csv"),
            "--robot",
            str(urdf),
            "--out",
            str(tmp_path / "r.npz"),
            "--quiet",
        ],
        ["intervals", str(urdf), "--out", str(tmp_path / "iv.png")],
    ):
        assert main(argv) == 2
        assert capsys.readouterr().err == expected
    assert not (tmp_path / "r.npz").exists()


def test_plot_says_a_csv_is_not_a_result(tmp_path, capsys) -> None:
    """Item 12: "pickled (object) data" for a CSV; now "not a qpnso result .npz"."""
    csv = tmp_path / "traj.csv"
    jump_csv(csv, rows=3)
    assert main(["plot", str(csv), "--out", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert "is not a qpnso result .npz" in err and "pickle" not in err and err.count("\n") == 1
    assert not (tmp_path / "x.png").exists()


def test_simulate_without_matplotlib_says_the_figure_was_skipped(tmp_path, capsys, monkeypatch) -> None:
    """Item 12: without matplotlib, simulate left no figure and no word; now it says so, and exits 0."""
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    out = tmp_path / "sim"
    assert (
        main(
            [
                "simulate",
                "--scenario",
                "A",
                "--strategy",
                "damped",
                "--duration-scale",
                "0.003",
                "--out",
                str(out),
                "--quiet",
            ]
        )
        == 0
    )
    assert {p.name for p in out.iterdir()} == {"result.npz", "summary.json"}
    err = capsys.readouterr().err
    assert "run.png skipped: matplotlib is not installed (pip install 'qpnso[plot]')" in err
    data = json.loads((out / "summary.json").read_text())  # the simulate summary counts slow ticks too
    assert "slow_ticks" in data and data["tick_time_max_ms"] > 0


# ------------------------------------------------------------ files that cannot be read or written (issue 31)
HOLD_CSV = str(SOURCE_TREE / "examples" / "trajectories" / "hold_lwr4p.csv")


def _writable(folder) -> bool:
    import tempfile

    try:
        with tempfile.NamedTemporaryFile(dir=folder):
            return True
    except OSError:
        return False


@pytest.fixture
def read_only_folder(tmp_path):
    """A folder this process cannot write in: a mode-0555 folder, or for root (whom modes do not stop) /sys."""
    from pathlib import Path

    folder = tmp_path / "read-only"
    folder.mkdir()
    folder.chmod(0o555)
    found = next((f for f in (folder, Path("/sys")) if f.is_dir() and not _writable(f)), None)
    if found is None:
        folder.chmod(0o755)
        pytest.skip("no folder on this machine that this process cannot write in")
    yield found
    folder.chmod(0o755)


@pytest.fixture(scope="module")
def result_file(tmp_path_factory) -> str:
    """A result.npz of a short solve: what ``qpnso plot`` reads."""
    folder = tmp_path_factory.mktemp("result")
    csv, res = str(folder / "hold.csv"), str(folder / "r.npz")
    argv = ["trajectory", "hold", "--center", "0.65,0,0.5", "--rpy-deg", "180,30,180", "--duration", "0.05"]
    assert main(argv + ["--out", csv]) == 0
    assert main(["solve", csv, "--out", res, "--quiet"]) == 0
    return res


FILE_OUTPUTS = {
    "trajectory": lambda out, tmp, res: ["trajectory", "hold", "--out", out],
    "solve": lambda out, tmp, res: ["solve", HOLD_CSV, "--out", out, "--quiet"],
    "solve --summary": lambda out, tmp, res: ["solve", HOLD_CSV, "--out", str(tmp / "r.npz"), "--summary", out],
    "plot": lambda out, tmp, res: ["plot", res, "--out", out],
    "intervals": lambda out, tmp, res: ["intervals", "--out", out],
    "bench fuzz": lambda out, tmp, res: ["bench", "fuzz", "-n", "20", "--quiet", "--out", out],
}
"""Commands whose output is one file: argv given the output path, tmp_path and a result file."""
FOLDER_OUTPUTS = {
    "simulate": ["simulate", "--scenario", "A", "--duration-scale", "0.01", "--quiet", "--out"],
    "compare": ["compare", "--scenario", "A", "--strategies", "qp", "--duration-scale", "0.01", "--quiet", "--out"],
    "study": ["study", "workspace", "--n", "2", "--workers", "1", "--quiet", "--out"],
    "experiment": ["experiment", "elbow", "--subjects", "1", "--trials", "1", "--duration-scale", "0.01", "--out"],
    "bench solvers": ["bench", "solvers", "--quick", "--quiet", "--out"],
}
"""Commands whose output is a folder: argv up to the output path."""
CASES = [(name, case) for name in [*FILE_OUTPUTS, *FOLDER_OUTPUTS] for case in ("kind", "under a file", "read-only")]


@pytest.mark.parametrize("command, case", CASES, ids=[f"{n}-{c}" for n, c in CASES])
def test_an_output_that_cannot_be_written_is_one_line_before_the_work(command, case, tmp_path, capsys, request) -> None:
    """Item 6: an output path that cannot be written (a folder given for a file or a file for a folder, a path
    under a file, a read-only place) gave a traceback, after the run; now one line naming the flag, the path
    and the problem, exit 2, before any work (nothing printed, nothing written)."""
    folder = command in FOLDER_OUTPUTS
    a_file = tmp_path / "a-file"
    a_file.write_text("")
    if case == "kind":
        out, expected = (a_file, "is a file, not a folder") if folder else (tmp_path, "is a folder, not a file")
    elif case == "under a file":
        out, expected = a_file / "sub" / "x", f"{a_file} is a file, not a folder"
    else:
        read_only = request.getfixturevalue("read_only_folder")
        out, expected = read_only / "x", f"cannot write in {read_only}"
    if folder:
        argv = FOLDER_OUTPUTS[command] + [str(out)]
    else:
        res = request.getfixturevalue("result_file") if command == "plot" else ""
        argv = FILE_OUTPUTS[command](str(out), tmp_path, res)
    capsys.readouterr()  # (what making the fixtures printed)
    flag = "--summary" if command == "solve --summary" else "--out"
    before = sorted(tmp_path.rglob("*"))
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert captured.err.startswith(f"qpnso: error: {flag} {out}: ") and captured.err.count("\n") == 1
    assert expected in captured.err and captured.out == ""
    assert sorted(tmp_path.rglob("*")) == before


def test_a_csv_that_is_not_utf8_is_one_line_naming_the_line(tmp_path, capsys) -> None:
    """Item 6: a trajectory or settings file that is not UTF-8 gave a UnicodeDecodeError traceback; now one line
    naming the file, the line and the byte, exit 2.  A byte-order mark (spreadsheets write one) is accepted."""
    text = "t,x,y,z,qx,qy,qz,qw\n0,0.65,0,0.5,1,0,0,0\n0.05,0.65,0,0.5,1,0,0,0\n"
    latin = tmp_path / "latin.csv"
    latin.write_bytes(text.encode() + "# température\n".encode("latin-1"))
    res = tmp_path / "r.npz"
    assert main(["solve", str(latin), "--out", str(res), "--quiet"]) == 2
    assert capsys.readouterr().err == (
        f"qpnso: error: {latin}: not UTF-8 text: line 4 has the byte 0xe9 (invalid continuation byte)\n"
    )
    config = tmp_path / "c.toml"
    config.write_bytes('[controller]\nstrategy = "qp" # défaut\n'.encode("latin-1"))
    assert main(["solve", HOLD_CSV, "--config", str(config), "--out", str(res), "--quiet"]) == 2
    assert capsys.readouterr().err == (
        f"qpnso: error: {config}: not UTF-8 text: line 2 has the byte 0xe9 (invalid continuation byte)\n"
    )
    assert not res.exists()
    from qpnso.control.trajectory import read_csv

    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + text.encode())
    assert len(read_csv(bom)) == 2


def test_a_file_that_cannot_be_written_after_all_is_one_line(tmp_path, capsys, monkeypatch, result_file) -> None:
    """Item 6: an OSError on a named file while writing (a disk that fills during the run...) is one line
    naming the file, exit 2, not a traceback."""
    import errno

    from qpnso.lab import plots

    def full_disk(arrays, out, title=""):
        raise OSError(errno.ENOSPC, "No space left on device", str(out))

    monkeypatch.setattr(plots, "plot_run", full_disk)
    out = tmp_path / "x.png"
    assert main(["plot", result_file, "--out", str(out)]) == 2
    assert capsys.readouterr().err == f"qpnso: error: {out}: No space left on device\n"
