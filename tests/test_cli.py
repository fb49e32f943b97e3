from pa_cli import __version__


def test_version(run_pa):
    code, out, _ = run_pa("--version")
    assert code == 0
    assert __version__ in out


def test_unknown_command_is_usage_error(run_pa):
    code, _, err = run_pa("no-such-command")
    assert code == 2
    assert "No such command" in err
