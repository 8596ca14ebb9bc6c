"""The ``gausslite`` command line as a user meets it: ``--version``, the grouped ``--help`` (product commands first,
research and benchmark commands apart), the export verbs (``export map|bag|models``) with the earlier spellings as
hidden deprecated aliases, and ``sim --help`` without the options of the report machinery (which still work)."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import numpy as np
import pytest

from gausslite.cli import PRODUCT_COMMANDS, RESEARCH_COMMANDS, build_parser, main
from gausslite.cli.cmd_export import upgrade_legacy_argv

REPO = Path(__file__).resolve().parents[2]


def help_text(capsys, *argv: str) -> str:
    """stdout of ``gausslite ARGV --help`` (in-process)."""
    with pytest.raises(SystemExit) as e:
        main([*argv, "--help"])
    assert e.value.code == 0
    return capsys.readouterr().out


# ---------------------------------------------------------------------------------------------- --version
def test_version_prints_the_installed_package_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"gausslite {version('gausslite')}"


@pytest.mark.integration  # starts a process
def test_version_of_the_console_script():
    exe = Path(sys.executable).with_name("gausslite")
    if not exe.is_file():
        pytest.skip("the gausslite console script is not installed next to this interpreter")
    r = subprocess.run([str(exe), "--version"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == f"gausslite {version('gausslite')}"


# ---------------------------------------------------------------------------------------------- --help
def test_help_lists_product_commands_first_and_research_commands_apart(capsys):
    text = help_text(capsys)
    lines = text.splitlines()
    product_at, research_at, options_at = (lines.index(h) for h in ("commands:", "research and benchmark commands:",
                                                                     "options:"))
    assert product_at < research_at < options_at
    listed = {}
    for i, line in enumerate(lines):
        words = line.split()
        if line.startswith("  ") and not line.startswith("   ") and words and words[0] in (*PRODUCT_COMMANDS,
                                                                                            *RESEARCH_COMMANDS):
            assert words[0] not in listed, f"{words[0]} listed twice"
            listed[words[0]] = i
    # every registered command is listed once, in its group, the product's in their documented order
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    registered = {a.dest for a in sub._get_subactions()}
    assert set(listed) == registered
    product = sorted((n for n in listed if n in PRODUCT_COMMANDS), key=listed.get)
    assert product == [n for n in PRODUCT_COMMANDS if n in registered]
    assert all(product_at < listed[n] < research_at for n in product)
    assert all(research_at < listed[n] < options_at for n in RESEARCH_COMMANDS if n in registered)
    assert {"ablate", "attention", "bench"} <= set(listed) and {"certs", "tokens", "export"} <= set(listed)
    assert "--version" in text
    # the deprecated spellings are not offered
    assert "export-bag" not in text and "export-models" not in text


# ---------------------------------------------------------------------------------------------- export
def _small_map(path: Path) -> int:
    from gausslite.viewer.export import write_map
    from gausslite.wire.codec import GaussianArrays

    r = np.random.default_rng(0)
    n = 300
    g = GaussianArrays(means=r.normal(size=(n, 3)).astype(np.float32), quats=r.normal(size=(n, 4)).astype(np.float32),
                       log_scales=np.full((n, 3), -3.0, np.float32), opacity_logits=np.ones(n, np.float32),
                       colors=r.uniform(size=(n, 3)).astype(np.float32), kappa=np.zeros(n, np.int64),
                       active=np.ones(n, bool))
    write_map(g, path)
    return n


def test_export_help_names_the_three_verbs(capsys):
    text = help_text(capsys, "export")
    for verb in ("map", "bag", "models"):
        assert f"    {verb} " in text, text
    assert "--out" in help_text(capsys, "export", "map") and "--storage" in help_text(capsys, "export", "bag")
    assert "--detector" in help_text(capsys, "export", "models")


def test_export_map_and_its_deprecated_spelling(tmp_path, capsys):
    n = _small_map(tmp_path / "m.ply")
    assert main(["export", "map", str(tmp_path / "m.ply"), "--out", str(tmp_path / "a.splat")]) == 0
    out = capsys.readouterr()
    assert f"{n:,} Gaussians" in out.out and "deprecated" not in out.err
    assert (tmp_path / "a.splat").stat().st_size == 32 * n
    # the earlier `export MAP --out FILE`: the same file, after one warning line on stderr
    assert main(["export", str(tmp_path / "m.ply"), "--out", str(tmp_path / "b.splat")]) == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "deprecated" in err and "gausslite export map" in err
    assert (tmp_path / "b.splat").read_bytes() == (tmp_path / "a.splat").read_bytes()
    assert main(["export", "map", str(tmp_path / "nope.ply"), "--out", str(tmp_path / "o.splat")]) == 2
    assert "gausslite export map: error:" in capsys.readouterr().err


def test_export_bag_and_models_old_spellings_run_the_new_commands(tmp_path, capsys):
    # export-models → export models: the same argument check, after the warning
    assert main(["export-models", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0] == "gausslite: warning: 'gausslite export-models' is deprecated; use 'gausslite export models'"
    assert "--detector and/or --segmenter" in err[1]
    assert main(["export", "models", "--out", str(tmp_path / "o")]) == 2
    assert "deprecated" not in capsys.readouterr().err
    # export-bag → export bag: a dataset that does not exist is the bag command's own error
    assert main(["export-bag", "--dataset", str(tmp_path / "none"), "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err
    assert "'gausslite export-bag' is deprecated; use 'gausslite export bag'" in err
    assert not (tmp_path / "b").exists()


def test_upgrade_legacy_argv_rewrites_only_the_old_spellings():
    assert upgrade_legacy_argv(["export-bag", "--dataset", "d"])[0] == ["export", "bag", "--dataset", "d"]
    assert upgrade_legacy_argv(["-v", "export-models", "--out", "o"])[0] == ["-v", "export", "models", "--out", "o"]
    assert upgrade_legacy_argv(["export", "m.ply", "--out", "x"])[0] == ["export", "map", "m.ply", "--out", "x"]
    assert upgrade_legacy_argv(["export", "--out", "x", "m.ply"])[0] == ["export", "map", "--out", "x", "m.ply"]
    for argv in (["export", "map", "m.ply"], ["export", "bag"], ["export", "--help"], ["export"], ["map", "export"],
                 ["sim", "--out", "export-bag"], []):
        assert upgrade_legacy_argv(list(argv)) == (argv, None)
    # the rewritten forms parse as the new commands
    args = build_parser().parse_args(upgrade_legacy_argv(["export", "m.ply", "--out", "x.spz"])[0])
    assert (args.command, args.export_what, args.map, args.out) == ("export", "map", "m.ply", "x.spz")


@pytest.mark.integration  # starts a process
def test_deprecation_warning_reaches_stderr_of_the_process(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    r = subprocess.run([sys.executable, "-m", "gausslite.cli", "export-models", "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 2
    assert r.stderr.splitlines()[0].startswith("gausslite: warning: 'gausslite export-models' is deprecated")


# ---------------------------------------------------------------------------------------------- sim
#: flags of the report machinery and the benchmarks: accepted, not listed
SIM_HIDDEN = ("--baseline", "--protocols", "--report-only", "--context-report", "--merge-only")
#: the options a user runs the simulation with (README.md, docs/fusion-and-deploy.md, docs/live.md, docs/ros.md)
SIM_VISIBLE = ("--dataset", "--out", "--config", "--set", "--tasks", "--downscale", "--max-frames", "--seeds-per-frame",
               "--realtime", "--rate", "--fps", "--budget", "--offline-report", "--attach", "--token", "--tls-ca",
               "--tls-client-cert", "--tls-client-key", "--rgb-topic")


def test_sim_help_hides_the_report_machinery_options_which_still_parse(capsys):
    text = help_text(capsys, "sim")
    for flag in SIM_HIDDEN:
        assert flag not in text, flag
    for flag in SIM_VISIBLE:
        assert flag in text, flag
    args = build_parser().parse_args(["sim", "--out", "o", "--baseline", "uniform", "--protocols", "sensor",
                                      "--report-only", "--context-report", "c.json", "--merge-only"])
    assert (args.baseline, args.protocols, args.report_only, args.context_report, args.merge_only) == \
        ("uniform", "sensor", True, "c.json", True)


def test_hidden_sim_options_keep_their_checks(tmp_path, capsys):
    assert main(["sim", "--out", str(tmp_path / "x"), "--report-only"]) == 2
    assert "--report-only needs --offline-report" in capsys.readouterr().err
    assert main(["sim", "--out", str(tmp_path / "x"), "--merge-only"]) == 2
    assert "--merge-only needs --context-report" in capsys.readouterr().err
    assert main(["sim", "--out", str(tmp_path / "x"), "--protocols", "sensor,oracle"]) == 2
    assert "choose among" in capsys.readouterr().err
