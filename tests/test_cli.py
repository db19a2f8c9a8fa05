"""The command line: reproduce list, a quick pendulum reproduction, clear errors."""

from __future__ import annotations

import json

from balustrade.cli import main


def test_reproduce_list_and_pendulum_quick(tmp_path, capsys):
    assert main(["reproduce", "list"]) == 0
    assert "pendulum" in capsys.readouterr().out.split()
    assert main(["reproduce", "pendulum", "--quick", "--out", str(tmp_path)]) == 0
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert (tmp_path / "pendulum_pcbf.png").stat().st_size > 10_000
    assert len(metrics["runs"]) == 5 and metrics["gamma_f"] > 0
    assert all(r["max_violation_in_S_PB"] <= 1e-6 for r in metrics["runs"])
    assert "gamma_f" in capsys.readouterr().out


def test_unknown_reproduction_is_a_clear_error(capsys):
    assert main(["reproduce", "no-such-example"]) == 2
    assert "unknown reproduction 'no-such-example'" in capsys.readouterr().err
