"""`pa config show`: the effective config of a preset or a file, every key described."""

from __future__ import annotations

from typing import Annotated

import typer

from pa_cli.cli.app import CONFIG_METAVAR, Group, Typer, app

config_app = Typer(cls=Group, name="config", help="Inspect configs: the presets, a file, every key with its unit.",
                    no_args_is_help=True)
app.add_typer(config_app)


@config_app.command("show")
def show_command(
    source: Annotated[str | None, typer.Argument(
        metavar=f"[{CONFIG_METAVAR}]", help="A preset (indoor, outdoor) or a YAML config file; none: the defaults.",
        show_default=False)] = None,
    advanced: Annotated[bool, typer.Option(
        "--advanced", help="Also list every key of the advanced section (without it, only the advanced keys that "
        "differ from the defaults).")] = False,
) -> None:
    """Print the effective config as YAML, each key commented with its description and unit: the user-facing sections (sensor, scene, refine, loops, map, execution), then advanced.

    The output is itself a config: save it, edit it and pass it to --config. docs/config.md lists every key.

    Example:

        pa config show outdoor

        pa config show indoor --advanced > my.yaml

        pa config show my.yaml
    """
    from pa_cli.config import dump_config, load_config, preset_names

    if source is None:
        title = "defaults"
    elif source in preset_names():
        title = f"preset {source}"
    else:
        title = source
    typer.echo(dump_config(load_config(source), title, advanced=advanced), nl=False)
