"""``undream evaluate``: a texture judged on any scenes, victims and simulator (:mod:`scheduler.evaluate`)."""
from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import click
import yaml

from undream.cli.errors import one_line_errors
from undream.cli.farm import settings_options
from undream.cli.options import local_settings, spp_option
from undream.errors import UndreamError

if TYPE_CHECKING:
    from undream.settings import Settings


DEFAULT_VICTIM = "bundled:classifier"  # a texture file names no victim


@click.command("evaluate")
@click.argument("texture", type=click.Path(path_type=Path))
@click.argument("scenes", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--victim", "victims", multiple=True,
              help="A victim (bundled:NAME, a folder or a hub id); repeat for several.  [default: the "
                   f"victim TEXTURE was attacked against (its runs' config), else {DEFAULT_VICTIM}]")
@click.option("--sim", default="mitsuba", show_default=True, help="The simulator that renders: mitsuba or blender.")
@spp_option("--spp", 32, "Samples per pixel of every frame.")
@click.option("--holdout", default="auto", show_default=True, callback=lambda _c, _p, v: _holdout(v),
              help="Which frames a run would hold out, judged apart: auto (every 4th), none, or a run "
                   "config's mapping in YAML: '{every: N, offset: K}' or '{frames: [0, 5]}'.")
@click.option("--label", default=None, help="The object's class (default: the scene's).")
@click.option("--print-capture", "capture", default=None, callback=lambda _c, _p, v: _capture(v),
              help="Judge every texture printed and photographed: a run config's eot_print mapping in YAML, "
                   "e.g. '{brightness: 0.1, gamma: 0.1, blur: 1, noise: 0.02}'; one draw per frame, none "
                   "of them an attack's.")
@click.option("--defence", "defence", default=None, callback=lambda _c, _p, v: _defence(v),
              help="Judge by each victim behind a defence: a run config's defence in YAML, e.g. '{jpeg: 75}' "
                   "or '[{median: 3}, {bits: 5}]' (docs/victims.md, Defended victims).")
@click.option("--json", "json_out", type=click.Path(path_type=Path), default=None, help="Write the rows as JSON.")
@click.option("--csv", "csv_out", type=click.Path(path_type=Path), default=None, help="Write the rows as CSV.")
@click.option("--frames-csv", "frames_out", type=click.Path(path_type=Path), default=None,
              help="Write one row per frame as CSV: its condition and split, and the victim's verdict with "
                   "the scene's texture and with TEXTURE (which views still hold); a detector's with its "
                   "top box and the object's true box (--json: all its kept boxes, at most 5).")
@settings_options
@one_line_errors
def evaluate_cmd(texture: Path, scenes: tuple[Path, ...], victims: tuple[str, ...], sim: str, spp: int,
                 holdout: Any, label: str | None, capture: Any, defence: Any, json_out: Path | None,
                 csv_out: Path | None, frames_out: Path | None, settings: Callable[..., "Settings"]) -> None:
    """Judge TEXTURE (a .npy, a .png, an `undream run` output folder, or a farm run or sweep by id or
    name: each of its runs' final textures) on SCENES (scene directories or spec files) by each
    victim, rendered by one simulator: per scene, victim and texture, on every frame and apart on the
    frames a run would attack and hold out, beside the scene's own texture."""
    from scheduler.evaluate import evaluate
    from undream.spec.io import atomic_write

    outputs = (("--json", json_out), ("--csv", csv_out), ("--frames-csv", frames_out))
    _check_outputs(outputs, texture, scenes, victims)  # before the renders, not after
    per_frame: list[dict[str, Any]] | None = None if frames_out is None and json_out is None else []
    attacked: list[str] | None = None if victims else []  # the runs' configs read only when --victim is not given
    textures = _textures(texture, settings, attacked)
    if attacked is not None:  # judged by the victim it was made against, not silently by another
        victims = tuple(attacked) or (DEFAULT_VICTIM,)
        _check_outputs(outputs, texture, scenes, victims)  # a victim folder named by the runs' config
        source = "the one TEXTURE was attacked against" if attacked else "the default"
        click.echo(f"victim: {', '.join(victims)} ({source}; --victim to choose)", err=True)
    rows = evaluate(textures, scenes, victims, sim=sim, spp=spp, holdout=holdout, label=label,
                    local=local_settings(), per_frame=per_frame, capture=capture, defence=defence)
    click.echo(_table(rows))
    if json_out is not None:
        document = {"texture": str(texture), "rows": rows, "frames": per_frame,
                    **({"print_capture": capture.to_json()} if capture is not None else {}),
                    **({"defence": defence.to_json()} if defence is not None else {})}
        atomic_write(json_out, json.dumps(document, indent=2, allow_nan=False) + "\n")
    if csv_out is not None:
        atomic_write(csv_out, _csv(rows))
    if frames_out is not None and per_frame is not None:
        atomic_write(frames_out, _csv([_flat(r) for r in per_frame]))


def _holdout(value: str) -> Any:
    """``--holdout`` as a run config's ``holdout``: ``auto``, ``none``, or the YAML mapping it spells
    (``{every: 2}`` was refused by a message that offered that very form: the text was never parsed)."""
    from undream.spec.yaml_strict import load

    if value.strip() in ("auto", "none"):
        return value.strip()
    try:
        parsed = load(value)
    except (yaml.YAMLError, UndreamError):
        parsed = None
    if not isinstance(parsed, dict):
        raise click.BadParameter(f"{value!r} is neither auto, none nor a YAML mapping such as "
                                 "'{every: 2}' or '{frames: [0, 5]}'")
    return parsed


def _mapping_option(value: str | None, config: Any) -> Any:
    """A YAML mapping option as ``config.from_json`` reads it (None when not given); one line otherwise."""
    from undream.spec.yaml_strict import load

    if value is None:
        return None
    try:
        return config.from_json(load(value))
    except (yaml.YAMLError, UndreamError) as err:
        raise click.BadParameter(f"{value!r}: {str(err).splitlines()[0]}") from None


def _capture(value: str | None) -> Any:
    """``--print-capture`` as a :class:`undream.spec.physical.PrintEotConfig` (None when not given)."""
    from undream.spec.physical import PrintEotConfig

    return _mapping_option(value, PrintEotConfig)


def _defence(value: str | None) -> Any:
    """``--defence`` as a :class:`undream.spec.defence.DefenceConfig` (None when not given)."""
    from undream.spec.defence import DefenceConfig

    return _mapping_option(value, DefenceConfig)


def _check_outputs(outputs: tuple[tuple[str, Path | None], ...], texture: Path, scenes: tuple[Path, ...],
                   victims: tuple[str, ...]) -> None:
    """The output files' rule (:func:`scheduler.preflight.check_output_files`) with every input of
    the command: the texture, the scenes, each victim that is a folder or file (``./myvictim``) and
    the settings file (``--settings``, else ``$UNDREAM_SETTINGS``); one line, before any render."""
    from scheduler.preflight import check_output_files
    from undream.settings import settings_file

    given = click.get_current_context().params.get("settings_file")  # taken by settings_options
    named = settings_file(given)
    check_output_files(outputs, inputs=(texture, *scenes, *map(Path, victims),
                                        None if named is None else Path(named)))


def _csv(rows: list[dict[str, Any]]) -> str:
    """``rows`` as CSV text, the columns of every row in the order first seen (a classifier's and a
    detector's verdicts differ)."""
    fields = list(dict.fromkeys(k for r in rows for k in r))
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, restval="", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


def _flat(row: dict[str, Any]) -> dict[str, Any]:
    """A per-frame row for the CSV: a box (``[x0, y0, x1, y1]``) as ``x0 y0 x1 y1`` in one cell, a
    detector's list of boxes left out (the JSON keeps them)."""
    return {k: " ".join(f"{v:g}" for v in value) if k.endswith("_box") and isinstance(value, list) else value
            for k, value in row.items() if not k.endswith("_boxes")}


def _textures(texture: Path, settings: Callable[..., "Settings"], victims: list[str] | None) -> dict[str, Any]:
    """TEXTURE as name → (texture, the scene it was optimised on): a file or output folder, else the
    farm's run or sweep by that id or name; ``victims``, when given, receives the victims its runs attacked."""
    from scheduler.evaluate import farm_textures, read_texture, run_scene, run_victim
    from undream.store import open_farm_store

    if texture.exists() or texture.suffix.lower() in (".npy", ".png"):
        found = {texture.name: (read_texture(texture), run_scene(texture) if texture.is_dir() else None)}
        if victims is not None and texture.is_dir() and (victim := run_victim(texture)):
            victims.append(victim)
        return found
    cfg = settings()
    return farm_textures(open_farm_store(cfg, create=False), str(texture), cfg.cache_dir, victims)


def _table(rows: list[dict]) -> str:
    """The rows as aligned columns, each as wide as its longest value: a victim, scene or texture is
    never cut (a cut name, ``undled:classifier-v3``, named no victim)."""
    cells = [(Path(r["scene"]).name, r["victim"], r["sim"], r["texture"], r["split"], str(r["frames"]), r["metric"],
              "n/a" if r["benign"] is None else f"{r['benign']:.3f}",
              "n/a" if r["adversarial"] is None else f"{r['adversarial']:.3f}") for r in rows]
    head = ("scene", "victim", "sim", "texture", "split", "frames", "metric", "benign", "texture")
    widths = [max(len(c) for c in column) for column in zip(head, *cells)]

    def line(values: tuple[str, ...]) -> str:
        padded = [v.rjust(w) if i in (5, 7) else v.ljust(w) for i, (v, w) in enumerate(zip(values, widths))]
        return (" ".join(padded[:6]) + "  " + " ".join(padded[6:8]) + " → " + values[8]).rstrip()

    return "\n".join(line(values) for values in [head, *cells])


COMMANDS = (evaluate_cmd,)
