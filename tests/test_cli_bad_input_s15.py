"""``balustrade sample`` grid options, ``balustrade train --data`` and ``balustrade bench
--only``: bad input is a :class:`~balustrade.errors.BalustradeError` naming the argument and
its shape (session 15, docs audit F: ``--lower 0 --upper 1 2`` on the 2-state pendulum raised
numpy's broadcast ``ValueError``, ``--upper`` below ``--lower`` a negative sample count, a zero
step an ``OverflowError``; a missing dataset folder was called "empty"; ``bench --only`` with a
typo ran nothing and exited 0)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from balustrade.cli import main
from balustrade.dsl import Box
from balustrade.errors import BalustradeError
from balustrade.learn.dataset import ShardedDataset, grid_plan
from balustrade.learn.sampler import snake_grid

X = Box.symmetric([0.5, 1.5])


@pytest.mark.parametrize("lower, upper, steps, match", [
    ([0.0], [1.0, 2.0], 0.1, r"lower .*expected shape \(2,\), got shape \(1,\)"),
    ([0.0, 0.0], [1.0, 1.0, 1.0], 0.1, r"upper .*expected shape \(2,\), got shape \(3,\)"),
    ([0.0, 0.0], [1.0, 1.0], [0.1, 0.1, 0.1], r"grid step .*expected shape \(2,\)"),
    ([0.0, 0.0], [-1.0, 1.0], 0.1, r"upper must be >= lower.*indices \[0\]"),
    ([0.0, 0.0], [1.0, 1.0], [0.0, 0.1], r"grid step .*finite and > 0"),
    ([0.0, np.nan], [1.0, 1.0], 0.1, r"lower .*NaN"),
])
def test_grid_plan_refuses_bad_boxes_naming_the_argument(lower, upper, steps, match):
    with pytest.raises(BalustradeError, match=match):
        grid_plan(X, lower, upper, steps)


def test_grid_plan_keeps_its_grid_for_good_input():
    """The checks change nothing for valid input: the points are the snake grid computed
    directly (scalar and per-state steps alike)."""
    chunks, config = grid_plan(X, [-0.2, -0.4], [0.2, 0.4], 0.2, band=False)
    pts = np.vstack([c.points for c in chunks])
    assert np.array_equal(pts, snake_grid([-0.2, -0.4], [0.2, 0.4], [0.2, 0.2]))
    assert config["steps"] == [0.2, 0.2] and config["n_grid"] == 3 * 5
    chunks2, _ = grid_plan(X, [-0.2, -0.4], [0.2, 0.4], [0.2, 0.2], band=False)
    assert np.array_equal(np.vstack([c.points for c in chunks2]), pts)


def test_cli_sample_bad_box_is_a_clean_error(tmp_path: Path, capsys):
    code = main(["sample", "--problem", "pendulum", "--out", str(tmp_path / "d"), "--quiet",
                 "--workers", "1", "--lower", "0", "--upper", "1", "2"])
    assert code == 2
    assert "grid_plan: lower" in capsys.readouterr().err


def test_missing_dataset_is_named_missing_not_empty(tmp_path: Path):
    with pytest.raises(BalustradeError, match="no dataset there"):
        ShardedDataset(tmp_path / "nothing").arrays()


def test_bench_only_without_a_match_is_an_error_not_a_silent_success(capsys):
    """``balustrade bench --only zzz`` ran nothing and returned 0; now it names the
    benchmarks there are (no benchmark runs: the check precedes the first import)."""
    assert main(["bench", "--only", "pendulum", "zzz"]) == 2
    err = capsys.readouterr().err
    assert "no benchmark matches ['zzz']" in err and "bench_pendulum" in err
