from pa_cli import __version__


def test_version(run_pa):
    code, out, _ = run_pa("--version")
    assert code == 0
    assert __version__ in out


def test_unknown_command_is_usage_error(run_pa):
    code, _, err = run_pa("no-such-command")
    assert code == 2
    assert "No such command" in err


def test_help_lists_every_command(run_pa):
    code, out, _ = run_pa("--help")
    assert code == 0
    for command in ("refine", "adjust", "perturb", "eval", "simulate"):
        assert command in out


def test_simulate_error_has_the_format_of_the_other_commands(run_pa, tmp_path):
    (tmp_path / "taken.txt").write_text("x")
    code, _, err = run_pa("simulate", "office", tmp_path, "--scans", "2")
    assert code == 1
    assert err.startswith(f"error: {tmp_path}: the folder is not empty")  # no blank line before it
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken.txt"]
