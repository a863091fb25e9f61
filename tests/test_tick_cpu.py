"""qpnso.lab.tick_cpu: the whole-tick thread CPU of Controller.step (issue 31, item 5's measurement)."""

from __future__ import annotations

import numpy as np

from qpnso.lab.tick_cpu import OVER_MS, TickCpu, main, tick_cpu


def test_a_row_gives_the_percentiles_and_the_share_over_one_ms() -> None:
    """The row's figures against NumPy's percentiles and a count of the ticks over 1 ms."""
    ms = np.array([0.1, 0.2, 0.3, 2.0, 0.5, 1.5, 0.4, 0.2, 0.1, 0.3])
    cells = [c.strip() for c in TickCpu("lwr4p", "qp", ms).row().strip("|").split("|")]
    assert cells[:3] == ["lwr4p", "qp", "10"]
    expected = [np.median(ms), np.percentile(ms, 99), np.percentile(ms, 99.9), ms.max()]
    np.testing.assert_allclose([float(c) for c in cells[3:7]], expected, atol=5e-4)
    assert float(cells[7]) == 100.0 * sum(m > OVER_MS for m in ms) / ms.size


def test_it_times_every_tick_and_prints_a_table(capsys) -> None:
    """A short run: one positive, finite CPU time per tick; the command line prints the header and a row."""
    run = tick_cpu("lwr4p", "rom", 30, ns0_offset=1.5)
    assert run.ms.shape == (30,) and np.all(np.isfinite(run.ms)) and np.all(run.ms >= 0.0)
    main(["--robots", "lwr4p", "--strategies", "damped", "--ticks", "20"])
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("| robot | strategy |") and lines[2].startswith("| lwr4p | damped | 20 |")
