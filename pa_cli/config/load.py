"""Reading a config (a preset shipped in the package, or a YAML file) and writing one back.

`load_config("indoor")` loads the preset `pa_cli/presets/indoor.yaml`; any other value is a path.
Keys of pa 0.1 are errors that name their new place or why they went (`pa_cli.config.renamed`); unknown keys are
errors with the closest valid key. `dump_config` writes the effective config as YAML with each
key's description as a comment; it loads back to the same config.
"""

from __future__ import annotations

import difflib
from importlib import resources
from pathlib import Path

from pydantic import BaseModel, ValidationError

from pa_cli.config.model import USER_SECTIONS, PaConfig
from pa_cli.config.renamed import CONSTANTS, REMOVED, RENAMED, RENAMED_IN
from pa_cli.errors import ConfigError
from pa_cli.io.files import read_input_bytes

CONFIG_HINT = "give --config indoor|outdoor|PATH; `pa config show --advanced` lists every key"
KEYS_HINT = "`pa config show --advanced` lists every key with its unit; docs/config.md describes them"


def preset_names() -> list[str]:
    """The presets shipped in the package (pa_cli/presets/NAME.yaml)."""
    folder = resources.files("pa_cli") / "presets"
    return sorted(entry.name[:-len(".yaml")] for entry in folder.iterdir() if entry.name.endswith(".yaml"))


def preset_path(name: str) -> Path:
    """The file of preset `name` (one of `preset_names()`)."""
    return Path(str(resources.files("pa_cli") / "presets" / f"{name}.yaml"))


def _one_line(text: str | None) -> str:
    return " ".join((text or "").split())


def _summary(section: type[BaseModel]) -> str:
    """A section's summary: the first paragraph of its docstring, on one line."""
    return _one_line((section.__doc__ or "").strip().split("\n\n")[0])


def _is_section(model: type[BaseModel], key: str) -> bool:
    annotation = model.model_fields[key].annotation
    return isinstance(annotation, type) and issubclass(annotation, BaseModel)


def dotted_keys(model: type[BaseModel] = PaConfig, prefix: str = "") -> list[str]:
    """Every key of `model` as a dotted path (`sensor.min_range_m`, `advanced.planes.min_points`, ...)."""
    keys: list[str] = []
    for key in model.model_fields:
        if _is_section(model, key):
            keys += dotted_keys(model.model_fields[key].annotation, f"{prefix}{key}.")
        else:
            keys.append(f"{prefix}{key}")
    return keys


def _suggestion(dotted: str, section: type[BaseModel] | None, prefix: str) -> str:
    """`; did you mean `KEY`?` for the valid key closest to `dotted`, or the valid keys of its section."""
    leaf = dotted.rsplit(".", 1)[-1]
    if section is not None:
        near = difflib.get_close_matches(leaf, list(section.model_fields), n=1)
        if near:
            return f"; did you mean `{prefix}{near[0]}`?"
    valid = dotted_keys()
    # every valid key by its dotted path and by its leaf, every old key by its own dotted path
    targets = {key: key for key in valid} | dict(RENAMED)
    near = difflib.get_close_matches(dotted, list(targets), n=1)
    if near:
        target = targets[near[0]]
        old = f" (`{near[0]}` before {RENAMED_IN})" if near[0] in RENAMED else ""
        return f"; did you mean `{target}`{old}?"
    by_leaf: dict[str, list[str]] = {}
    for key in valid:
        by_leaf.setdefault(key.rsplit(".", 1)[-1], []).append(key)
    near = difflib.get_close_matches(leaf, list(by_leaf), n=1)
    if near:
        return "; did you mean " + " or ".join(f"`{k}`" for k in by_leaf[near[0]][:3]) + "?"
    if section is not None:
        return f"; the keys of `{prefix.rstrip('.') or 'the file'}` are {', '.join(section.model_fields)}"
    return ""


def _old_key(dotted: str) -> str | None:
    """The error for a key of pa 0.1 that moved, became a constant or was removed, else None."""
    if dotted in RENAMED:
        return f"`{dotted}` was renamed to `{RENAMED[dotted]}` ({RENAMED_IN})"
    if dotted in CONSTANTS:
        module, name = CONSTANTS[dotted]
        return f"`{dotted}` is no longer a setting ({RENAMED_IN}): it is the constant {name} in {module}"
    if dotted in REMOVED:
        return f"`{dotted}` is no longer a setting ({RENAMED_IN}): {REMOVED[dotted]}"
    return None


def _flatten(data: dict, prefix: str) -> list[str]:
    keys: list[str] = []
    for key, value in data.items():
        keys += _flatten(value, f"{prefix}{key}.") if isinstance(value, dict) else [f"{prefix}{key}"]
    return keys


def _key_problems(data: dict, model: type[BaseModel], prefix: str = "") -> list[str]:
    """The keys of `data` that `model` does not have: each an old key's new place or the closest valid key."""
    problems: list[str] = []
    for key, value in data.items():
        dotted = f"{prefix}{key}"
        if key in model.model_fields:
            if _is_section(model, key) and isinstance(value, dict):
                problems += _key_problems(value, model.model_fields[key].annotation, f"{dotted}.")
            continue
        old_section = any(old.startswith(f"{dotted}.") for old in (*RENAMED, *CONSTANTS, *REMOVED))
        if old_section and isinstance(value, dict):
            for inner in _flatten(value, f"{dotted}."):
                problems.append(_old_key(inner) or f"unknown key `{inner}`{_suggestion(inner, None, '')}")
        elif old_section:
            problems.append(f"`{dotted}` is no longer a section ({RENAMED_IN}); its keys moved to the sections of "
                            "`pa config show --advanced`")
        else:
            problems.append(_old_key(dotted) or f"unknown key `{dotted}`{_suggestion(dotted, model, prefix)}")
    return problems


def _without_empty_sections(data: dict, model: type[BaseModel]) -> dict:
    """`data` without the sections that are null: a section whose keys are all commented out is empty."""
    kept = {}
    for key, value in data.items():
        if key in model.model_fields and _is_section(model, key):
            if value is None:
                continue
            if isinstance(value, dict):
                value = _without_empty_sections(value, model.model_fields[key].annotation)
        kept[key] = value
    return kept


def _read_text(path: Path) -> str:
    raw = read_input_bytes(path, "config", CONFIG_HINT)
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        lineno = raw[:exc.start].count(b"\n") + 1
        kind = "binary content (a NUL byte)" if b"\0" in raw else f"a byte that is not UTF-8 (0x{raw[exc.start]:02x})"
        raise ConfigError(f"{path}:{lineno}: {kind}; a config file is YAML text in UTF-8 "
                          "(re-save it as UTF-8).") from None
    if "\0" in text:
        lineno = text[:text.index("\0")].count("\n") + 1
        raise ConfigError(f"{path}:{lineno}: binary content (a NUL byte); a config file is YAML text.")
    return text


def _parse(text: str, path: Path) -> PaConfig:
    import yaml  # here: commands without a config file skip its import

    try:
        data = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc}).") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of sections ({', '.join(USER_SECTIONS)}, advanced).")

    data = _without_empty_sections(data, PaConfig)
    problems = _key_problems(data, PaConfig)
    if not problems:
        try:
            return PaConfig.model_validate(data)
        except ValidationError as exc:
            problems = [f"`{'.'.join(str(p) for p in err['loc'])}`: {err['msg']} (got {err['input']!r})"
                        for err in exc.errors()]
    lines = [f"{path}: {problem}" + ("" if problem.endswith("?") else ".") for problem in problems]
    raise ConfigError("\n".join(lines) + f"\n({KEYS_HINT}.)")


def load_config(source: Path | str | None) -> PaConfig:
    """The config of a preset name (`indoor`, `outdoor`: pa_cli/presets) or of a YAML file; keys not given keep
    their defaults. None gives the defaults."""
    if source is None:
        return PaConfig()
    if str(source) in preset_names():
        path = preset_path(str(source))
    else:
        path = Path(source)
        if not path.exists():
            raise ConfigError(f"{path}: no such config file, and not a preset (presets: "
                              f"{', '.join(preset_names())}); {CONFIG_HINT}.")
    return _parse(_read_text(path), path)


def _section_lines(section: BaseModel, default: BaseModel, indent: str, changed_only: bool) -> list[str]:
    """The YAML lines of one section's keys (and subsections), each with its description as a comment."""
    import yaml

    lines: list[str] = []
    for key in type(section).model_fields:
        value = getattr(section, key)
        if isinstance(value, BaseModel):
            inner = _section_lines(value, getattr(default, key), indent + "  ", changed_only)
            if inner:
                lines += [f"{indent}{key}:  # {_summary(type(value))}", *inner]
            continue
        if changed_only and value == getattr(default, key):
            continue
        text = yaml.safe_dump({key: value}, default_flow_style=True, width=1000).strip()
        text = text[1:-1] if text.startswith("{") else text  # "{key: value}" -> "key: value"
        lines.append(f"{indent}{text}  # {_one_line(type(section).model_fields[key].description)}")
    return lines


def dump_config(config: PaConfig, title: str = "effective configuration", advanced: bool = True) -> str:
    """The config as YAML text, every section and key commented with its description: the user-facing sections,
    then `advanced` (every key, or with `advanced=False` only the keys that differ from the defaults). It loads
    back (`load_config`) to `config`."""
    lines = [f"# pa config: {title}.",
             "# Keys left out keep their defaults. `pa config show [indoor|outdoor|PATH]` prints the effective config,",
             "# `--advanced` every advanced key too; docs/config.md describes every key.", ""]
    defaults = PaConfig()
    for name in USER_SECTIONS:
        section = getattr(config, name)
        lines += [f"{name}:  # {_summary(type(section))}",
                  *_section_lines(section, getattr(defaults, name), "  ", changed_only=False), ""]
    inner = _section_lines(config.advanced, defaults.advanced, "  ", changed_only=not advanced)
    if inner:
        note = "" if advanced else " Only the keys that differ from the defaults (`--advanced`: all)."
        lines += [f"advanced:  # {_summary(type(config.advanced))}{note}", *inner, ""]
    else:
        lines += ["# advanced: every key at its default (`pa config show --advanced` lists them).", ""]
    return "\n".join(lines)
