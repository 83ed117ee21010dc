"""``psgateway check-config`` on a state machine service: a chart that does not load names its line."""

from __future__ import annotations

from pathlib import Path

import pytest

from gateway.cli import main


def test_check_config_names_the_chart_its_line_and_the_reason(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    chart = tmp_path / "dock.scxml"
    chart.write_text(
        '<scxml xmlns="http://www.w3.org/2005/07/scxml" initial="a">\n'
        '  <state id="a">\n'
        '    <transition event="x" target="charging"/>\n'
        "  </state>\n"
        "</scxml>\n"
    )
    config = tmp_path / "site.toml"
    config.write_text(
        f"""
[[services]]
name = "missions"
type = "statemachine"
options = {{ charts = {{ dock = "{chart}", patrol = "builtin:patrol" }} }}
"""
    )
    assert main(["check-config", str(config)]) == 2
    err = capsys.readouterr().err
    assert "services (missions)" in err and "chart 'dock'" in err
    assert "line 3: no state with id 'charging'" in err


def test_check_config_accepts_the_shipped_patrol_chart(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "site.toml"
    config.write_text(
        """
[[services]]
name = "missions"
type = "statemachine"
options = { charts = { patrol = "builtin:patrol" }, autostart = ["patrol"] }
"""
    )
    assert main(["check-config", str(config)]) == 0
    assert "fine (1 services" in capsys.readouterr().out


def test_a_relative_chart_path_starts_at_the_config_files_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    site = tmp_path / "site"
    (site / "charts").mkdir(parents=True)
    (site / "charts" / "dock.scxml").write_text(
        '<scxml xmlns="http://www.w3.org/2005/07/scxml" initial="a"><state id="a"/></scxml>\n'
    )
    config = site / "site.toml"
    config.write_text(
        """
[[services]]
name = "missions"
type = "statemachine"
options = { charts = { dock = "charts/dock.scxml", patrol = "builtin:patrol" } }
"""
    )
    monkeypatch.chdir(tmp_path)  # the gateway runs elsewhere: the chart is still found beside the config
    assert main(["check-config", str(config)]) == 0, capsys.readouterr().err
    assert "fine (1 services" in capsys.readouterr().out
